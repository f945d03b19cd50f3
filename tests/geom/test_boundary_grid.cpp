// Tests for the boundary-layer extrusion (mpmgeom::extrude_layer, extrude_layer_2d, layer_1d):
// exact volumes and offsets on flat walls in any orientation, shell volumes on spheres and
// cylinders, local shrinking in concave regions, sub-layers, and the alpha-basis maps.

#include "mpmgeom/boundary_grid.hpp"
#include "support/shapes.hpp"

#include <gtest/gtest.h>

#include <algorithm>
#include <array>
#include <cmath>
#include <functional>
#include <limits>
#include <map>
#include <numbers>
#include <random>
#include <stdexcept>
#include <string>
#include <utility>
#include <vector>

#include <Eigen/Geometry>

namespace {

using mpm::test::icosphere;
using mpmgeom::BoundaryGrid;
using mpmgeom::LayerOptions;
using mpmgeom::LayerReport;
using mpmgeom::MeshError;
using mpmgeom::TriangleMesh;
constexpr double kPi = std::numbers::pi;

Eigen::Matrix3d random_rotation(std::mt19937& rng) {
  std::normal_distribution<double> normal;
  Eigen::Quaterniond q(normal(rng), normal(rng), normal(rng), normal(rng));
  return q.normalized().toRotationMatrix();
}

/// n x n squares of [0, side]^2 in the plane z = 0, two triangles each, normals +z.
TriangleMesh planar_square(int n, double side) {
  TriangleMesh mesh;
  mesh.V.resize((n + 1) * (n + 1), 3);
  for (int j = 0; j <= n; ++j) {
    for (int i = 0; i <= n; ++i) mesh.V.row(j * (n + 1) + i) << side * i / n, side * j / n, 0.0;
  }
  mesh.F.resize(2 * n * n, 3);
  for (int j = 0; j < n; ++j) {
    for (int i = 0; i < n; ++i) {
      const int a = j * (n + 1) + i, b = a + 1, c = a + n + 1, d = c + 1;
      mesh.F.row(2 * (j * n + i)) << a, b, d;
      mesh.F.row(2 * (j * n + i) + 1) << a, d, c;
    }
  }
  mesh.part = Eigen::VectorXi::Zero(mesh.F.rows());
  mesh.part_names = {"plane"};
  return mesh;
}

/// Open tube of radius R about the z axis, z in [0, L], with normals outward.
TriangleMesh tube(double R, double L, int around, int rings) {
  TriangleMesh mesh;
  mesh.V.resize(around * (rings + 1), 3);
  for (int j = 0; j <= rings; ++j) {
    for (int i = 0; i < around; ++i) {
      const double phi = 2.0 * kPi * i / around;
      mesh.V.row(j * around + i) << R * std::cos(phi), R * std::sin(phi), L * j / rings;
    }
  }
  mesh.F.resize(2 * around * rings, 3);
  for (int j = 0; j < rings; ++j) {
    for (int i = 0; i < around; ++i) {
      const int a = j * around + i, b = j * around + (i + 1) % around, c = a + around,
                d = b + around;
      mesh.F.row(2 * (j * around + i)) << a, b, d;
      mesh.F.row(2 * (j * around + i) + 1) << a, d, c;
    }
  }
  return mesh;
}

/// A groove along y: two flat faces of width 1 and length 1 meeting at the line x = z = 0 with an
/// opening angle `opening` (radians, < pi: concave seen from the material inside the groove),
/// symmetric about the z axis, n x n squares per face; normals into the groove.
TriangleMesh groove(double opening, int n) {
  const double half = opening / 2.0;
  const Eigen::Vector3d right(std::sin(half), 0.0, std::cos(half)),
      left(-std::sin(half), 0.0, std::cos(half));
  TriangleMesh mesh;
  // Columns i = -n..n across (negative: left face), rows j = 0..n along y.
  mesh.V.resize((2 * n + 1) * (n + 1), 3);
  auto index = [n](int i, int j) { return j * (2 * n + 1) + (i + n); };
  for (int j = 0; j <= n; ++j) {
    for (int i = -n; i <= n; ++i) {
      const Eigen::Vector3d across = (i < 0 ? left : right) * (std::abs(i) / double(n));
      mesh.V.row(index(i, j)) = (across + Eigen::Vector3d(0.0, double(j) / n, 0.0)).transpose();
    }
  }
  mesh.F.resize(2 * 2 * n * n, 3);
  int f = 0;
  for (int j = 0; j < n; ++j) {
    for (int i = -n; i < n; ++i) {
      const int a = index(i, j), b = index(i + 1, j), c = index(i, j + 1), d = index(i + 1, j + 1);
      // (b - a) runs across the groove towards +x, (d - a) along +y: the normal
      // (b - a) x (d - a) points into the groove, i.e. counter-clockwise seen from the material.
      mesh.F.row(f++) << a, b, d;
      mesh.F.row(f++) << a, d, c;
    }
  }
  return mesh;
}

double signed_volume(const BoundaryGrid& grid, const Eigen::MatrixXi& facets) {
  double v = 0.0;
  for (Eigen::Index f = 0; f < facets.rows(); ++f) {
    const Eigen::Vector3d a = grid.nodes.row(facets(f, 0)), b = grid.nodes.row(facets(f, 1)),
                          c = grid.nodes.row(facets(f, 2));
    v += a.dot(b.cross(c)) / 6.0;
  }
  return v;
}

double mesh_area(const TriangleMesh& mesh) {
  double area = 0.0;
  for (Eigen::Index f = 0; f < mesh.F.rows(); ++f) {
    const Eigen::Vector3d a = mesh.V.row(mesh.F(f, 0)), b = mesh.V.row(mesh.F(f, 1)),
                          c = mesh.V.row(mesh.F(f, 2));
    area += 0.5 * (b - a).cross(c - a).norm();
  }
  return area;
}

double mesh_volume(const TriangleMesh& mesh) {
  double v = 0.0;
  for (Eigen::Index f = 0; f < mesh.F.rows(); ++f) {
    const Eigen::Vector3d a = mesh.V.row(mesh.F(f, 0)), b = mesh.V.row(mesh.F(f, 1)),
                          c = mesh.V.row(mesh.F(f, 2));
    v += a.dot(b.cross(c)) / 6.0;
  }
  return v;
}

/// Natural coordinates of the corners of a cell of the grid's dimension.
std::vector<Eigen::Vector3d> cell_corners(int dimension) {
  if (dimension == 1) return {{0, 0, 0}, {1, 0, 0}};
  if (dimension == 2) return {{0, 0, 0}, {1, 0, 0}, {0, 1, 0}, {1, 1, 0}};
  std::vector<Eigen::Vector3d> corners;
  for (const double z : {0.0, 1.0}) {
    for (const auto& [r, s] : {std::pair{0.0, 0.0}, std::pair{1.0, 0.0}, std::pair{0.0, 1.0}}) {
      corners.emplace_back(r, s, z);
    }
  }
  return corners;
}

/// Smallest det(dx/dxi) at the corners of all cells, and at the cell centres, each divided by
/// that cell's straight-prism value (2 * wall-facet area * t / K, or length * t / K).
double min_corner_jacobian(const BoundaryGrid& grid) {
  const int dim = grid.dimension;
  std::vector<Eigen::Vector3d> points = cell_corners(dim);
  points.push_back(dim == 2 ? Eigen::Vector3d(0.5, 0.5, 0) : Eigen::Vector3d(1 / 3., 1 / 3., 0.5));
  double worst = std::numeric_limits<double>::infinity();
  const auto F = grid.wall_facets.rows();
  for (std::size_t c = 0; c < grid.cell_count(); ++c) {
    const Eigen::Index f = static_cast<Eigen::Index>(c) % F;
    double nominal = grid.thickness / grid.layers;
    if (dim == 3) {
      const Eigen::Vector3d a = grid.nodes.row(grid.wall_facets(f, 0)),
                            b = grid.nodes.row(grid.wall_facets(f, 1)),
                            d = grid.nodes.row(grid.wall_facets(f, 2));
      nominal *= (b - a).cross(d - a).norm();
    } else if (dim == 2) {
      nominal *=
          (grid.nodes.row(grid.wall_facets(f, 1)) - grid.nodes.row(grid.wall_facets(f, 0))).norm();
    }
    for (const auto& xi : points) {
      const Eigen::Matrix3d J = mpmgeom::cell_jacobian(grid, c, xi);
      worst = std::min(worst, J.topLeftCorner(dim, dim).determinant() / nominal);
    }
  }
  return worst;
}

void expect_consistent_layout(const BoundaryGrid& grid, const LayerReport& report) {
  const auto N = grid.nodes.rows();
  const auto F = grid.wall_facets.rows();
  const auto P = N / (grid.layers + 1);
  EXPECT_EQ(report.cells, grid.cell_count());
  EXPECT_EQ(report.nodes, static_cast<std::size_t>(N));
  EXPECT_EQ(grid.cells.rows(), grid.layers * F);
  EXPECT_EQ(grid.cells.cols(), grid.nodes_per_cell());
  EXPECT_EQ(grid.node_on_wall.sum(), P);
  EXPECT_EQ(grid.node_on_interface.sum(), P);
  EXPECT_EQ(grid.interface_facets.rows(), F);
  EXPECT_EQ(grid.wall_facet_part.size(), F);
  EXPECT_EQ(grid.cell_part.size(), grid.cells.rows());
  EXPECT_EQ(grid.cell_layer.size(), grid.cells.rows());
  for (Eigen::Index f = 0; f < F; ++f) {
    for (Eigen::Index i = 0; i < grid.wall_facets.cols(); ++i) {
      EXPECT_EQ(grid.node_on_wall(grid.wall_facets(f, i)), 1);
      EXPECT_EQ(grid.node_on_interface(grid.interface_facets(f, i)), 1);
      // The wall facet is the bottom of the layer-0 cell, the interface facet the top of the
      // layer K-1 cell of the same column.
      EXPECT_EQ(grid.cells(f, i), grid.wall_facets(f, i));
      EXPECT_EQ(grid.cells((grid.layers - 1) * F + f, grid.wall_facets.cols() + i),
                grid.interface_facets(f, i));
    }
  }
  EXPECT_GT(report.min_jacobian, 0.0);
}

TEST(BoundaryLayer, FlatSquareInAnyOrientationHasExactVolumeAndOffsets) {
  std::mt19937 rng(20240611);
  std::uniform_real_distribution<double> shift(-5.0, 5.0);
  const double side = 1.3, t = 0.17;
  for (const int n : {1, 7}) {
    for (int trial = 0; trial < 10; ++trial) {
      const Eigen::Matrix3d R = random_rotation(rng);
      const Eigen::Vector3d b(shift(rng), shift(rng), shift(rng));
      TriangleMesh mesh = planar_square(n, side);
      for (Eigen::Index v = 0; v < mesh.V.rows(); ++v) {
        mesh.V.row(v) = (R * mesh.V.row(v).transpose() + b).transpose();
      }
      const Eigen::Vector3d normal = R.col(2);
      LayerOptions options;
      options.thickness = t;
      LayerReport report;
      const BoundaryGrid grid = mpmgeom::extrude_layer(mesh, options, &report);
      SCOPED_TRACE("n = " + std::to_string(n) + ", trial " + std::to_string(trial));
      expect_consistent_layout(grid, report);

      const double area = side * side;
      EXPECT_NEAR(report.volume, area * t, 1e-9 * area * t);
      EXPECT_NEAR(report.wall_measure, area, 1e-12 * area);
      EXPECT_NEAR(report.interface_measure, report.wall_measure, 1e-12 * area);
      EXPECT_NEAR(report.min_jacobian, 1.0, 1e-9);
      EXPECT_EQ(report.columns_shrunk, 0u);
      EXPECT_GT(min_corner_jacobian(grid), 1.0 - 1e-9);

      const auto P = mesh.V.rows();
      EXPECT_TRUE(grid.nodes.topRows(P) == mesh.V);  // wall nodes are the mesh vertices
      for (Eigen::Index v = 0; v < grid.nodes.rows(); ++v) {
        const double height = (grid.nodes.row(v).transpose() - b).dot(normal);
        const double expected = grid.node_on_interface(v) ? t : 0.0;
        EXPECT_NEAR(height, expected, 1e-12 * (1.0 + b.norm()));
        EXPECT_NEAR((grid.node_normals.row(v).transpose() - normal).norm(), 0.0, 1e-12);
      }
      // Gamma faces into the layer, Phi away from it: both along the wall normal.
      for (Eigen::Index f = 0; f < grid.wall_facets.rows(); ++f) {
        for (const auto* facets : {&grid.wall_facets, &grid.interface_facets}) {
          const Eigen::Vector3d a = grid.nodes.row((*facets)(f, 0)),
                                c1 = grid.nodes.row((*facets)(f, 1)),
                                c2 = grid.nodes.row((*facets)(f, 2));
          EXPECT_GT((c1 - a).cross(c2 - a).dot(normal), 0.0);
        }
      }
    }
  }
}

TEST(BoundaryLayer, SphereWithMaterialOutsideGivesTheShellVolume) {
  const double R = 1.0, t = 0.1;
  const TriangleMesh mesh = icosphere(4, R, true);
  LayerOptions options;
  options.thickness = t;
  LayerReport report;
  const BoundaryGrid grid = mpmgeom::extrude_layer(mesh, options, &report);
  expect_consistent_layout(grid, report);

  // The inscribed polyhedron (5120 facets) lacks 0.2 % of the sphere's area and volume, so the
  // 1 % asked for is a test of the extrusion, not of the tessellation; against the polyhedron's
  // own shell (radial offsets would scale it by (R + t) / R) the match is much tighter.
  const double exact = 4.0 / 3.0 * kPi * (std::pow(R + t, 3) - std::pow(R, 3));
  const double polyhedral = mesh_volume(mesh) * (std::pow(1.0 + t / R, 3) - 1.0);
  EXPECT_NEAR(report.volume, exact, 0.01 * exact);
  EXPECT_NEAR(report.volume, polyhedral, 1e-3 * polyhedral);
  const double phi_area = 4.0 * kPi * (R + t) * (R + t);
  EXPECT_NEAR(report.interface_measure, phi_area, 0.01 * phi_area);
  EXPECT_NEAR(report.wall_measure, mesh_area(mesh), 1e-12 * phi_area);

  // Exact volume: the layer is bounded by Phi and Gamma alone (the sides of neighbouring
  // columns cancel), so the divergence theorem must agree with the quadrature to round-off.
  const double divergence =
      signed_volume(grid, grid.interface_facets) - signed_volume(grid, grid.wall_facets);
  EXPECT_NEAR(report.volume, divergence, 1e-12 * exact);
  // ... and with a quadrature of cell_jacobian exact for det J (degree 1 in (r, s), 2 in zeta):
  // edge midpoints on the triangle times Simpson in zeta.
  double quadrature = 0.0;
  for (std::size_t c = 0; c < grid.cell_count(); ++c) {
    for (const auto& [r, s] : {std::pair{0.5, 0.0}, std::pair{0.5, 0.5}, std::pair{0.0, 0.5}}) {
      for (const auto& [z, w] : {std::pair{0.0, 1.0}, std::pair{0.5, 4.0}, std::pair{1.0, 1.0}}) {
        quadrature += w / 36.0 * mpmgeom::cell_jacobian(grid, c, {r, s, z}).determinant();
      }
    }
  }
  EXPECT_NEAR(report.volume, quadrature, 1e-12 * exact);

  EXPECT_EQ(report.columns_shrunk, 0u);
  // The offsets spread on a convex wall, so det J is smallest on the wall, where it is the
  // nominal value times the cosine between vertex and facet normals; that angle is below the
  // angle an edge subtends at the centre.
  double longest_edge = 0.0;
  for (Eigen::Index f = 0; f < mesh.F.rows(); ++f) {
    for (int i = 0; i < 3; ++i) {
      longest_edge = std::max(
          longest_edge, (mesh.V.row(mesh.F(f, i)) - mesh.V.row(mesh.F(f, (i + 1) % 3))).norm());
    }
  }
  EXPECT_GT(report.min_jacobian, std::cos(longest_edge / R));
  EXPECT_LE(report.min_jacobian, 1.0);
  EXPECT_GE(min_corner_jacobian(grid), report.min_jacobian * (1.0 - 1e-12));
  for (Eigen::Index v = 0; v < grid.nodes.rows(); ++v) {
    if (!grid.node_on_interface(v)) continue;
    EXPECT_NEAR(grid.nodes.row(v).norm(), R + t, 1e-3 * t);
    EXPECT_GT(grid.node_normals.row(v).dot(grid.nodes.row(v)), 0.999 * (R + t));
  }
}

TEST(BoundaryLayer, SphereWithMaterialInsideGivesTheInnerShell) {
  const double R = 1.0, t = 0.3;
  const TriangleMesh mesh = icosphere(4, R, false);
  LayerOptions options;
  options.thickness = t;
  LayerReport report;
  const BoundaryGrid grid = mpmgeom::extrude_layer(mesh, options, &report);
  expect_consistent_layout(grid, report);
  const double exact = 4.0 / 3.0 * kPi * (std::pow(R, 3) - std::pow(R - t, 3));
  EXPECT_NEAR(report.volume, exact, 0.01 * exact);
  const double phi_area = 4.0 * kPi * (R - t) * (R - t);
  EXPECT_NEAR(report.interface_measure, phi_area, 0.01 * phi_area);
  // Phi faces out of the layer and Gamma into it, whichever way the wall is wound.
  const double divergence =
      signed_volume(grid, grid.interface_facets) - signed_volume(grid, grid.wall_facets);
  EXPECT_NEAR(report.volume, divergence, 1e-12 * exact);
  EXPECT_EQ(report.columns_shrunk, 0u);
  EXPECT_LT(report.min_jacobian, 1.0);  // converging offsets
  EXPECT_GT(min_corner_jacobian(grid), 0.0);
}

TEST(BoundaryLayer, TubeWithMaterialOutsideGivesTheCylindricalShell) {
  const double R = 0.5, L = 2.0, t = 0.1;
  const TriangleMesh mesh = tube(R, L, 96, 24);
  LayerOptions options;
  options.thickness = t;
  LayerReport report;
  const BoundaryGrid grid = mpmgeom::extrude_layer(mesh, options, &report);
  expect_consistent_layout(grid, report);
  const double exact = kPi * ((R + t) * (R + t) - R * R) * L;
  EXPECT_NEAR(report.volume, exact, 0.01 * exact);
  EXPECT_NEAR(report.interface_measure, 2.0 * kPi * (R + t) * L, 0.01 * 2.0 * kPi * (R + t) * L);
  EXPECT_EQ(report.columns_shrunk, 0u);
  EXPECT_GT(min_corner_jacobian(grid), 0.0);
}

/// Offset length (|interface node - wall node|) of every wall point.
std::vector<double> offsets(const BoundaryGrid& grid) {
  const auto P = grid.nodes.rows() / (grid.layers + 1);
  std::vector<double> length(static_cast<std::size_t>(P));
  for (Eigen::Index v = 0; v < P; ++v) {
    length[v] = (grid.nodes.row(grid.layers * P + v) - grid.nodes.row(v)).norm();
  }
  return length;
}

/// Largest (|offset_u - offset_v| - |x_u - x_v|) over the wall edges: <= 0 if the offset grows
/// by at most its distance along the wall.
double worst_offset_slope_excess(const BoundaryGrid& grid) {
  const std::vector<double> length = offsets(grid);
  double worst = -std::numeric_limits<double>::infinity();
  for (Eigen::Index f = 0; f < grid.wall_facets.rows(); ++f) {
    const auto n = grid.wall_facets.cols();
    for (Eigen::Index i = 0; i < n; ++i) {
      const int u = grid.wall_facets(f, i), v = grid.wall_facets(f, (i + 1) % n);
      worst = std::max(
          worst, std::abs(length[u] - length[v]) - (grid.nodes.row(u) - grid.nodes.row(v)).norm());
    }
  }
  return worst;
}

TEST(BoundaryLayer, ConcaveGrooveIsShrunkLocallyUntilNoCellFolds) {
  for (const double opening_deg : {90.0, 60.0}) {
    SCOPED_TRACE("opening " + std::to_string(opening_deg) + " degrees");
    const int n = 10;
    const double h = 1.0 / n, opening = opening_deg * kPi / 180.0;
    const TriangleMesh mesh = groove(opening, n);
    LayerOptions options;
    options.thickness = 0.3;  // three wall spacings: the offsets cross near the crease
    const double t = options.thickness;
    LayerReport report;
    const BoundaryGrid grid = mpmgeom::extrude_layer(mesh, options, &report);
    expect_consistent_layout(grid, report);
    EXPECT_GT(report.columns_shrunk, 0u);
    EXPECT_GT(report.max_shrink, 0.0);
    EXPECT_LE(report.max_shrink, 1.0 - options.min_thickness_fraction + 1e-12);
    EXPECT_GT(min_corner_jacobian(grid), 0.0);
    EXPECT_LT(report.volume, report.wall_measure * t);
    EXPECT_GT(report.volume, 0.5 * report.wall_measure * t);

    // No overlap: every column stays on its own side of the bisector plane x = 0 (the medial
    // axis of the groove), where it cannot meet the columns of the other face.
    const auto P = mesh.V.rows();
    for (Eigen::Index v = 0; v < P; ++v) {
      const double wall_x = mesh.V(v, 0), top_x = grid.nodes(P + v, 0);
      if (std::abs(wall_x) < 1e-12) {
        EXPECT_NEAR(top_x, 0.0, 0.05 * t) << "crease point " << v;
      } else {
        EXPECT_GT(top_x * wall_x, 0.0) << "point " << v;
      }
    }

    // Shrinking is local. A face point at distance d from the crease has its normal offset
    // reach the bisector plane at height d tan(opening / 2): columns within
    // t / tan(opening / 2) of the crease stop short of it (with a margin of 10 %), and those
    // within h of them may fold; grading restores the full thickness within another t.
    const double reach = t / (0.9 * std::tan(opening / 2.0)) + h + t;
    const std::vector<double> length = offsets(grid);
    for (Eigen::Index v = 0; v < mesh.V.rows(); ++v) {
      const double d = std::hypot(mesh.V(v, 0), mesh.V(v, 2));
      if (d > reach) {
        EXPECT_NEAR(length[v], t, 1e-12) << "point " << v;
      }
      EXPECT_GE(length[v], options.min_thickness_fraction * t * (1.0 - 1e-12));
    }
    // ... and graded: Phi rises from the shrunk crease at no more than 45 degrees.
    EXPECT_LE(worst_offset_slope_excess(grid), 1e-12);

    // The crease points at the two open ends have a lopsided fan of triangles (two on one face,
    // one on the other); their normal is reset to the bisector of the faces.
    EXPECT_GE(report.crease_normals, 2u);
    for (const Eigen::Index end : {Eigen::Index{n}, Eigen::Index{n * (2 * n + 1) + n}}) {
      ASSERT_NEAR(mesh.V(end, 0), 0.0, 1e-15);
      EXPECT_NEAR((grid.node_normals.row(end) - Eigen::RowVector3d(0, 0, 1)).norm(), 0.0, 1e-12);
    }

    // Without shrinking the same fold cannot be removed: a one-line error naming the place.
    options.min_thickness_fraction = 1.0;
    try {
      mpmgeom::extrude_layer(mesh, options);
      ADD_FAILURE() << "expected MeshError";
    } catch (const MeshError& e) {
      const std::string what = e.what();
      EXPECT_NE(what.find("boundary layer: cannot extrude the layer at triangle"),
                std::string::npos)
          << what;
      EXPECT_NE(what.find(" near ("), std::string::npos) << what;
      EXPECT_EQ(what.find('\n'), std::string::npos);
    }
  }
}

TEST(BoundaryLayer, FoldsBeyondTheAllowedShrinkingAreReported) {
  // A 30-degree groove with t = 8 h: next to the crease the columns would have to shrink to
  // about h tan(15 deg) / t = 3 % of t, below the default limit of 10 %.
  LayerOptions options;
  options.thickness = 0.8;
  EXPECT_THROW(mpmgeom::extrude_layer(groove(kPi / 6.0, 10), options), MeshError);
  // Allowing it, the layer is built.
  options.min_thickness_fraction = 0.01;
  LayerReport report;
  const BoundaryGrid grid = mpmgeom::extrude_layer(groove(kPi / 6.0, 10), options, &report);
  EXPECT_GT(report.max_shrink, 0.9);
  EXPECT_GT(min_corner_jacobian(grid), 0.0);
}

/// The unit cube [0, 1]^3 with n x n squares per face, welded, normals outward or inward.
TriangleMesh cube(int n, bool outward) {
  struct Face {
    Eigen::Vector3d origin, u, v;  // u x v = outward normal
  };
  const std::array<Face, 6> faces = {{{{0, 0, 0}, {0, 1, 0}, {1, 0, 0}},
                                      {{0, 0, 1}, {1, 0, 0}, {0, 1, 0}},
                                      {{0, 0, 0}, {0, 0, 1}, {0, 1, 0}},
                                      {{1, 0, 0}, {0, 1, 0}, {0, 0, 1}},
                                      {{0, 0, 0}, {1, 0, 0}, {0, 0, 1}},
                                      {{0, 1, 0}, {0, 0, 1}, {1, 0, 0}}}};
  std::map<std::array<long, 3>, int> index;
  std::vector<Eigen::Vector3d> points;
  std::vector<std::array<int, 3>> triangles;
  auto point = [&](const Eigen::Vector3d& x) {
    const std::array<long, 3> key = {std::lround(x.x() * n), std::lround(x.y() * n),
                                     std::lround(x.z() * n)};
    const auto [it, added] = index.emplace(key, static_cast<int>(points.size()));
    if (added) points.push_back(x);
    return it->second;
  };
  for (const auto& face : faces) {
    auto at = [&](int i, int j) { return point(face.origin + face.u * i / n + face.v * j / n); };
    for (int j = 0; j < n; ++j) {
      for (int i = 0; i < n; ++i) {
        const int a = at(i, j), b = at(i + 1, j), c = at(i, j + 1), d = at(i + 1, j + 1);
        triangles.push_back(outward ? std::array{a, b, d} : std::array{a, d, b});
        triangles.push_back(outward ? std::array{a, d, c} : std::array{a, c, d});
      }
    }
  }
  TriangleMesh mesh;
  mesh.V.resize(static_cast<Eigen::Index>(points.size()), 3);
  for (std::size_t i = 0; i < points.size(); ++i) {
    mesh.V.row(static_cast<Eigen::Index>(i)) = points[i].transpose();
  }
  mesh.F.resize(static_cast<Eigen::Index>(triangles.size()), 3);
  for (std::size_t f = 0; f < triangles.size(); ++f) {
    const auto& [a, b, c] = triangles[f];
    mesh.F.row(static_cast<Eigen::Index>(f)) << a, b, c;
  }
  return mesh;
}

TEST(BoundaryLayer, CubeEdgesAndCornersFromBothSides) {
  LayerOptions options;
  options.thickness = 0.2;  // two wall spacings
  const double t = options.thickness;
  LayerReport report;
  // Material outside: convex edges and corners; the layer spreads there.
  BoundaryGrid grid = mpmgeom::extrude_layer(cube(10, true), options, &report);
  expect_consistent_layout(grid, report);
  EXPECT_EQ(report.columns_shrunk, 0u);
  EXPECT_GT(min_corner_jacobian(grid), 0.0);
  EXPECT_NEAR(report.wall_measure, 6.0, 1e-12);
  // Every Phi node lies within t of the cube, and the set of such points is convex, so the layer
  // lies inside the exact offset shell 6 t + 3 pi t^2 + 4/3 pi t^3; the columns spread at the
  // convex edges, so it is more than the six slabs.
  EXPECT_LT(report.volume, 6 * t + 3 * kPi * t * t + 4.0 / 3.0 * kPi * t * t * t);
  EXPECT_GT(report.volume, 6 * t);
  EXPECT_NEAR(report.volume,
              signed_volume(grid, grid.interface_facets) - signed_volume(grid, grid.wall_facets),
              1e-12);
  // Material inside: concave edges and corners; shrunk near them only.
  grid = mpmgeom::extrude_layer(cube(10, false), options, &report);
  expect_consistent_layout(grid, report);
  EXPECT_GT(report.columns_shrunk, 0u);
  EXPECT_GT(min_corner_jacobian(grid), 0.0);
  EXPECT_LE(worst_offset_slope_excess(grid), 1e-12);
  const double inner_band = 1.0 - std::pow(1.0 - 2.0 * t, 3);  // the exact inward offset band
  EXPECT_LT(report.volume, inner_band);
  EXPECT_GT(report.volume, 0.5 * inner_band);
  EXPECT_NEAR(report.volume,
              signed_volume(grid, grid.interface_facets) - signed_volume(grid, grid.wall_facets),
              1e-12);
  // As in the groove (90 degrees), only points within t / 0.9 + h + t of an edge may be shrunk.
  // On a face the distance to the nearest edge is the middle one of the distances to the three
  // pairs of faces.
  const std::vector<double> length = offsets(grid);
  const auto P = grid.wall_facets.maxCoeff() + 1;
  for (Eigen::Index v = 0; v < P; ++v) {
    const Eigen::Vector3d x = grid.nodes.row(v);
    std::array<double, 3> to_face = {std::min(x.x(), 1 - x.x()), std::min(x.y(), 1 - x.y()),
                                     std::min(x.z(), 1 - x.z())};
    std::sort(to_face.begin(), to_face.end());
    if (to_face[1] > t / 0.9 + 0.1 + t + 1e-9) {
      EXPECT_NEAR(length[v], t, 1e-12) << x.transpose();
    }
    // No overlap: a column from the interior of a face stays closer to that face than to any
    // other (the medial axis of the cube's interior separates the faces' columns).
    if (to_face[1] > 1e-12) {
      const Eigen::Vector3d top = grid.nodes.row(P + v);
      int own = 0;
      for (int i = 0; i < 3; ++i) {
        if (std::min(x[i], 1 - x[i]) < 1e-12) own = i;
      }
      const double own_distance = std::min(top[own], 1 - top[own]);
      for (int i = 0; i < 3; ++i) {
        if (i != own) {
          EXPECT_LT(own_distance, std::min(top[i], 1 - top[i])) << x.transpose();
        }
      }
    }
  }
}

TEST(BoundaryLayer, FacingWallsCloserThanTwiceTheThicknessStopShortOfTheMidplane) {
  // A floor and a ceiling (another part) a gap g < 2 t apart, both with the material between
  // them: each layer stops at 0.9 of the midplane height instead of running into the other.
  const double gap = 0.15, t = 0.1;
  const TriangleMesh floor = planar_square(6, 1.0);
  TriangleMesh both;
  both.V.resize(2 * floor.V.rows(), 3);
  both.V << floor.V, floor.V;
  both.V.bottomRows(floor.V.rows()).col(2).setConstant(gap);
  both.F.resize(2 * floor.F.rows(), 3);
  both.F.topRows(floor.F.rows()) = floor.F;
  const Eigen::MatrixX3i ceiling =
      floor.F.rowwise().reverse().array() + static_cast<int>(floor.V.rows());
  both.F.bottomRows(floor.F.rows()) = ceiling;
  both.part = Eigen::VectorXi::Zero(both.F.rows());
  both.part.tail(floor.F.rows()).setOnes();
  both.part_names = {"floor", "ceiling"};
  LayerOptions options;
  options.thickness = t;
  LayerReport report;
  const BoundaryGrid grid = mpmgeom::extrude_layer(both, options, &report);
  expect_consistent_layout(grid, report);
  EXPECT_EQ(report.columns_shrunk, static_cast<std::size_t>(both.V.rows()));
  // The midplane lies at g / 2; the limit is taken with a relative tolerance of 1e-3 on the
  // distances, so it is within 1e-3 of that.
  const double height = 0.9 * gap / 2.0;
  const auto P = both.V.rows();
  for (Eigen::Index v = 0; v < P; ++v) {
    const double top = grid.nodes(P + v, 2), wall = both.V(v, 2);
    EXPECT_NEAR(std::abs(top - wall), height, 1e-3 * height) << "point " << v;
  }
  EXPECT_NEAR(report.volume, 2.0 * height, 2e-3 * height);
  EXPECT_GT(min_corner_jacobian(grid), 0.0);
}

TEST(BoundaryLayer, SubLayersSplitEachColumnWithoutChangingTheLayer) {
  const TriangleMesh mesh = icosphere(3, 1.0, true);
  LayerOptions one;
  one.thickness = 0.2;
  LayerOptions three = one;
  three.layers = 3;
  LayerReport r1, r3;
  const BoundaryGrid g1 = mpmgeom::extrude_layer(mesh, one, &r1);
  const BoundaryGrid g3 = mpmgeom::extrude_layer(mesh, three, &r3);
  expect_consistent_layout(g3, r3);
  EXPECT_EQ(r3.cells, 3 * r1.cells);
  EXPECT_EQ(r3.nodes, 2 * r1.nodes);  // (K + 1) levels of wall points
  EXPECT_NEAR(r3.volume, r1.volume, 1e-12 * r1.volume);
  EXPECT_NEAR(r3.interface_measure, r1.interface_measure, 1e-12 * r1.interface_measure);
  EXPECT_NEAR(r3.min_jacobian, r1.min_jacobian, 1e-12);
  const auto F = g1.wall_facets.rows();
  for (Eigen::Index c = 0; c < g3.cells.rows(); ++c) EXPECT_EQ(g3.cell_layer(c), c / F);
  for (Eigen::Index f = 0; f < F; ++f) {
    for (int i = 0; i < 3; ++i) {
      EXPECT_LT((g3.nodes.row(g3.interface_facets(f, i)) - g1.nodes.row(g1.interface_facets(f, i)))
                    .norm(),
                1e-14);
    }
  }
  EXPECT_GT(min_corner_jacobian(g3), 0.0);
}

TEST(BoundaryLayer, PartsFollowTheirTriangles) {
  TriangleMesh mesh = planar_square(4, 1.0);
  mesh.part_names = {"left", "right"};
  for (Eigen::Index f = 0; f < mesh.F.rows(); ++f) {
    mesh.part(f) = mesh.V(mesh.F(f, 0), 0) < 0.5 ? 0 : 1;
  }
  LayerOptions options;
  options.thickness = 0.1;
  options.layers = 2;
  const BoundaryGrid grid = mpmgeom::extrude_layer(mesh, options);
  EXPECT_EQ(grid.part_names, mesh.part_names);
  EXPECT_EQ(grid.wall_facet_part, mesh.part);
  for (Eigen::Index c = 0; c < grid.cells.rows(); ++c) {
    EXPECT_EQ(grid.cell_part(c), mesh.part(c % mesh.F.rows()));
  }
}

TEST(BoundaryLayer, UnreferencedVerticesAndUnweldedSeams) {
  // Wall nodes are the referenced vertices in their original order; an unused vertex gets none.
  TriangleMesh mesh = planar_square(2, 1.0);
  const auto used = mesh.V.rows();
  mesh.V.conservativeResize(used + 1, 3);
  mesh.V.row(used) << 5.0, 5.0, 5.0;
  LayerOptions options;
  options.thickness = 0.1;
  LayerReport report;
  BoundaryGrid grid = mpmgeom::extrude_layer(mesh, options, &report);
  EXPECT_EQ(grid.nodes.rows(), 2 * used);
  EXPECT_TRUE(grid.nodes.topRows(used) == mesh.V.topRows(used));
  // Two triangles that share an edge only by position (not welded): each has its own columns,
  // and the coincident points do not limit each other.
  TriangleMesh seam;
  seam.V.resize(6, 3);
  seam.V << 0, 0, 0, 1, 0, 0, 1, 1, 0, 0, 0, 0, 1, 1, 0, 0, 1, 0;
  seam.F.resize(2, 3);
  seam.F << 0, 1, 2, 3, 4, 5;
  grid = mpmgeom::extrude_layer(seam, options, &report);
  EXPECT_EQ(report.columns_shrunk, 0u);
  EXPECT_NEAR(report.volume, 0.1, 1e-15);
  EXPECT_EQ(grid.part_names, std::vector<std::string>{"wall"});
}

TEST(BoundaryLayer, RejectsInvalidOptionsAndDefectiveWalls) {
  const TriangleMesh mesh = planar_square(2, 1.0);
  for (const auto& change : std::vector<std::function<void(LayerOptions&)>>{
           [](LayerOptions& o) { o.thickness = 0.0; }, [](LayerOptions& o) { o.thickness = -1.0; },
           [](LayerOptions& o) { o.thickness = std::numeric_limits<double>::quiet_NaN(); },
           [](LayerOptions& o) { o.thickness = std::numeric_limits<double>::infinity(); },
           [](LayerOptions& o) { o.layers = 0; }, [](LayerOptions& o) { o.normal_smoothing = -1; },
           [](LayerOptions& o) { o.min_thickness_fraction = 0.0; },
           [](LayerOptions& o) { o.min_thickness_fraction = 1.5; }}) {
    LayerOptions options;
    options.thickness = 0.1;
    change(options);
    std::string why;
    EXPECT_FALSE(options.valid(&why));
    EXPECT_FALSE(why.empty());
    EXPECT_THROW(mpmgeom::extrude_layer(mesh, options), std::invalid_argument);
    EXPECT_THROW(mpmgeom::extrude_layer_2d(Eigen::MatrixX2d::Random(3, 2), false, options),
                 std::invalid_argument);
    EXPECT_THROW(mpmgeom::layer_1d(0.0, 1, options), std::invalid_argument);
  }
  LayerOptions options;
  options.thickness = 0.1;
  EXPECT_TRUE(options.valid());
  EXPECT_THROW(mpmgeom::extrude_layer(TriangleMesh{}, options), MeshError);
  EXPECT_THROW(mpmgeom::extrude_layer_2d(Eigen::MatrixX2d(1, 2), false, options), MeshError);
  EXPECT_THROW(mpmgeom::extrude_layer_2d(Eigen::MatrixX2d(0, 2), false, options), MeshError);
  EXPECT_THROW(mpmgeom::layer_1d(0.0, 0, options), std::invalid_argument);
  EXPECT_THROW(mpmgeom::layer_1d(std::nan(""), 1, options), MeshError);

  TriangleMesh bad = mesh;
  bad.F(0, 1) = 99;
  EXPECT_THROW(mpmgeom::extrude_layer(bad, options), MeshError);
  bad = mesh;
  bad.V(0, 0) = std::numeric_limits<double>::infinity();
  EXPECT_THROW(mpmgeom::extrude_layer(bad, options), MeshError);
  // Two triangles on one edge wound opposite ways: a vertex normal cancels or leaves a triangle.
  bad = planar_square(1, 1.0);
  std::swap(bad.F(1, 1), bad.F(1, 2));
  EXPECT_THROW(mpmgeom::extrude_layer(bad, options), MeshError);
  // A closed polyline must not repeat its first point.
  Eigen::MatrixX2d square(5, 2);
  square << 0, 0, 1, 0, 1, 1, 0, 1, 0, 0;
  EXPECT_THROW(mpmgeom::extrude_layer_2d(square, true, options), MeshError);
}

TEST(BoundaryLayer, StraightPolylineAtAnyAngleHasExactArea) {
  std::mt19937 rng(7);
  std::uniform_real_distribution<double> angle(0.0, 2.0 * kPi), shift(-3.0, 3.0);
  const double t = 0.25, L = 2.0;
  for (int trial = 0; trial < 10; ++trial) {
    const double a = angle(rng);
    const Eigen::Vector2d dir(std::cos(a), std::sin(a)), left(-dir.y(), dir.x()),
        b(shift(rng), shift(rng));
    const int n = 1 + trial;
    Eigen::MatrixX2d line(n + 1, 2);
    for (int i = 0; i <= n; ++i) line.row(i) = (b + dir * (L * i / n)).transpose();
    LayerOptions options;
    options.thickness = t;
    options.layers = 1 + trial % 3;
    LayerReport report;
    const BoundaryGrid grid = mpmgeom::extrude_layer_2d(line, false, options, "floor", &report);
    expect_consistent_layout(grid, report);
    EXPECT_NEAR(report.volume, L * t, 1e-12 * L * t);
    EXPECT_NEAR(report.wall_measure, L, 1e-12 * L);
    EXPECT_NEAR(report.interface_measure, L, 1e-12 * L);
    EXPECT_NEAR(report.min_jacobian, 1.0, 1e-12);
    EXPECT_GT(min_corner_jacobian(grid), 1.0 - 1e-12);
    EXPECT_EQ(grid.part_names, std::vector<std::string>{"floor"});
    for (Eigen::Index v = 0; v < grid.nodes.rows(); ++v) {
      const double level = static_cast<double>(v / (n + 1)) / options.layers;
      EXPECT_NEAR((grid.nodes.row(v).transpose() - b).dot(left), level * t, 1e-12);
    }
    // Gamma and Phi segments run with the polyline: their left normal points into the layer
    // (Gamma) and out of it, towards the bulk (Phi).
    for (Eigen::Index s = 0; s < grid.wall_facets.rows(); ++s) {
      for (const auto* facets : {&grid.wall_facets, &grid.interface_facets}) {
        const Eigen::Vector2d d = grid.nodes.row((*facets)(s, 1)) - grid.nodes.row((*facets)(s, 0));
        EXPECT_GT(d.dot(dir), 0.0);
      }
    }
  }
}

Eigen::MatrixX2d circle(double R, int n, bool counter_clockwise) {
  Eigen::MatrixX2d points(n, 2);
  for (int i = 0; i < n; ++i) {
    const double phi = (counter_clockwise ? 1.0 : -1.0) * 2.0 * kPi * i / n;
    points.row(i) << R * std::cos(phi), R * std::sin(phi);
  }
  return points;
}

TEST(BoundaryLayer, CirclePolylineGivesTheAnnulus) {
  const double R = 1.0, t = 0.2;
  LayerOptions options;
  options.thickness = t;
  LayerReport report;
  // Clockwise: the material on the left is outside the circle.
  BoundaryGrid grid = mpmgeom::extrude_layer_2d(circle(R, 128, false), true, options, "c", &report);
  expect_consistent_layout(grid, report);
  double exact = kPi * ((R + t) * (R + t) - R * R);
  EXPECT_NEAR(report.volume, exact, 0.01 * exact);
  EXPECT_NEAR(report.interface_measure, 2 * kPi * (R + t), 0.01 * 2 * kPi * (R + t));
  // Smallest on the wall, where the bisector normal makes half the turning angle with a segment.
  const double half_turn = kPi / 128;
  EXPECT_NEAR(report.min_jacobian, std::cos(half_turn), 1e-12);
  // Counter-clockwise: the material is inside.
  grid = mpmgeom::extrude_layer_2d(circle(R, 128, true), true, options, "c", &report);
  expect_consistent_layout(grid, report);
  exact = kPi * (R * R - (R - t) * (R - t));
  EXPECT_NEAR(report.volume, exact, 0.01 * exact);
  // Smallest on Phi, whose segments are shorter by (R - t) / R.
  EXPECT_NEAR(report.min_jacobian, (R - t) / R * std::cos(half_turn), 1e-12);
  EXPECT_EQ(report.columns_shrunk, 0u);
  EXPECT_GT(min_corner_jacobian(grid), 0.0);
}

/// The unit square's boundary with `n` segments per side, counter-clockwise if ccw.
Eigen::MatrixX2d square_loop(int n, bool ccw) {
  Eigen::MatrixX2d points(4 * n, 2);
  const std::array<Eigen::Vector2d, 4> corner = {Eigen::Vector2d(0, 0), Eigen::Vector2d(1, 0),
                                                 Eigen::Vector2d(1, 1), Eigen::Vector2d(0, 1)};
  for (int side = 0; side < 4; ++side) {
    for (int i = 0; i < n; ++i) {
      const double u = double(i) / n;
      points.row(side * n + i) = ((1 - u) * corner[side] + u * corner[(side + 1) % 4]).transpose();
    }
  }
  if (!ccw) points = points.colwise().reverse().eval();
  return points;
}

TEST(BoundaryLayer, ClosedSquareShrinksOnlyAtTheInnerCorners) {
  const int n = 10;
  const double t = 0.3;  // three segments: the offsets from two sides cross near each corner
  LayerOptions options;
  options.thickness = t;
  options.layers = 2;
  LayerReport report;
  // Material inside: the corners are concave seen from it.
  BoundaryGrid grid =
      mpmgeom::extrude_layer_2d(square_loop(n, true), true, options, "box", &report);
  expect_consistent_layout(grid, report);
  EXPECT_GT(report.columns_shrunk, 0u);
  EXPECT_LT(report.columns_shrunk, static_cast<std::size_t>(4 * n));
  EXPECT_GT(min_corner_jacobian(grid), 0.0);
  EXPECT_LE(worst_offset_slope_excess(grid), 1e-12);
  EXPECT_LT(report.volume, 4.0 * t);
  // No less than the inward offset band of the exact square, 4 t - 4 t^2, minus what the
  // shrinking took: at least the band left between the corners.
  EXPECT_GT(report.volume, 0.5 * (4.0 * t - 4.0 * t * t));
  // No overlap: Phi is a simple polygon (columns from the two sides of a corner do not cross,
  // although no single quad folds where they would).
  const auto& phi = grid.interface_facets;
  auto cross = [](const Eigen::Vector2d& a, const Eigen::Vector2d& b) {
    return a.x() * b.y() - a.y() * b.x();
  };
  for (Eigen::Index i = 0; i < phi.rows(); ++i) {
    for (Eigen::Index j = i + 2; j < phi.rows(); ++j) {
      if (i == 0 && j == phi.rows() - 1) continue;  // neighbours on the closed loop
      const Eigen::Vector2d a = grid.nodes.row(phi(i, 0)), b = grid.nodes.row(phi(i, 1)),
                            c = grid.nodes.row(phi(j, 0)), d = grid.nodes.row(phi(j, 1));
      const bool apart = cross(b - a, c - a) * cross(b - a, d - a) > 0.0 ||
                         cross(d - c, a - c) * cross(d - c, b - c) > 0.0;
      EXPECT_TRUE(apart) << "Phi segments " << i << " and " << j << " cross";
    }
  }
  // Material outside: convex corners, nothing to shrink, the corners add area.
  grid = mpmgeom::extrude_layer_2d(square_loop(n, false), true, options, "box", &report);
  expect_consistent_layout(grid, report);
  EXPECT_EQ(report.columns_shrunk, 0u);
  EXPECT_GT(report.volume, 4.0 * t);
  EXPECT_LT(report.volume, 4.0 * t + kPi * t * t);
  EXPECT_GT(min_corner_jacobian(grid), 0.0);
}

TEST(BoundaryLayer, OneDimensionalLayerOnBothSides) {
  LayerOptions options;
  options.thickness = 0.3;
  options.layers = 3;
  for (const int side : {1, -1}) {
    LayerReport report;
    const BoundaryGrid grid = mpmgeom::layer_1d(2.0, side, options, "end", &report);
    expect_consistent_layout(grid, report);
    EXPECT_EQ(grid.dimension, 1);
    ASSERT_EQ(grid.nodes.rows(), 4);
    for (int k = 0; k <= 3; ++k) EXPECT_NEAR(grid.nodes(k, 0), 2.0 + side * 0.1 * k, 1e-15);
    EXPECT_EQ(grid.wall_facets(0, 0), 0);
    EXPECT_EQ(grid.interface_facets(0, 0), 3);
    EXPECT_NEAR(report.volume, 0.3, 1e-15);
    EXPECT_EQ(report.min_jacobian, 1.0);
    for (std::size_t c = 0; c < grid.cell_count(); ++c) {
      const double dx_dzeta = mpmgeom::cell_jacobian(grid, c, Eigen::Vector3d(0.5, 0, 0))(0, 0);
      EXPECT_NEAR(dx_dzeta, side * 0.1, 1e-15);  // negative for side = -1 ...
      EXPECT_GT(side * dx_dzeta, 0.0);           // ... positive once sign-adjusted
      EXPECT_EQ(grid.node_normals(grid.cells(c, 0), 0), side);
      EXPECT_NEAR(mpmgeom::cell_point(grid, c, Eigen::Vector3d(0, 0, 0))[0],
                  grid.nodes(grid.cells(c, 0), 0), 0.0);  // wall-side node first
    }
  }
}

TEST(BoundaryLayer, CellMapsAgreeWithFiniteDifferences) {
  std::mt19937 rng(3);
  std::uniform_real_distribution<double> unit(0.0, 1.0);
  LayerOptions options;
  options.thickness = 0.3;
  options.layers = 2;
  std::vector<BoundaryGrid> grids;
  grids.push_back(mpmgeom::extrude_layer(groove(kPi / 3.0, 6), options));  // shrunk, distorted
  grids.push_back(mpmgeom::extrude_layer(icosphere(2, 1.0, false), options));
  grids.push_back(mpmgeom::extrude_layer_2d(square_loop(6, true), true, options));
  grids.push_back(mpmgeom::layer_1d(-1.0, -1, options));
  for (const auto& grid : grids) {
    const int dim = grid.dimension;
    std::uniform_int_distribution<std::size_t> pick(0, grid.cell_count() - 1);
    // Corners map onto the cell's nodes.
    const auto corners = cell_corners(dim);
    for (int trial = 0; trial < 5; ++trial) {
      const std::size_t c = pick(rng);
      for (std::size_t k = 0; k < corners.size(); ++k) {
        const auto node = grid.cells(static_cast<Eigen::Index>(c), static_cast<Eigen::Index>(k));
        EXPECT_LT(
            (mpmgeom::cell_point(grid, c, corners[k]).head(dim) - grid.nodes.row(node).transpose())
                .norm(),
            1e-14);
      }
    }
    for (int trial = 0; trial < 50; ++trial) {
      const std::size_t c = pick(rng);
      Eigen::Vector3d xi(unit(rng), unit(rng), unit(rng));
      if (dim == 3 && xi[0] + xi[1] > 1.0) xi.head<2>() = Eigen::Vector2d(1.0, 1.0) - xi.head<2>();
      const Eigen::Matrix3d J = mpmgeom::cell_jacobian(grid, c, xi);
      const double h = 1e-6;
      for (int j = 0; j < dim; ++j) {
        Eigen::Vector3d step = Eigen::Vector3d::Zero();
        step[j] = h;
        const Eigen::Vector3d fd =
            (mpmgeom::cell_point(grid, c, xi + step) - mpmgeom::cell_point(grid, c, xi - step)) /
            (2 * h);
        // The map is at most quadratic in xi, so central differences are exact up to round-off.
        EXPECT_LT((fd.head(dim) - J.col(j).head(dim)).norm(), 1e-8) << "dimension " << dim;
      }
      if (dim > 1) {
        EXPECT_GT(J.topLeftCorner(dim, dim).determinant(), 0.0);
      }
    }
  }
}

}  // namespace
