// Tests for mpmgeom::LayerLocator and mpmgeom::ClosedSurface (locator.hpp).
//
// Layers are built by hand here (not with extrude_layer) so that these tests depend only on the
// cell definitions of boundary_grid.hpp. Inside/outside is checked against CGAL's
// Side_of_triangle_mesh (exact predicates) and, for boxes, against the analytic answer.

#include "mpmgeom/locator.hpp"
#include "support/shapes.hpp"

#include <CGAL/AABB_face_graph_triangle_primitive.h>
#include <CGAL/AABB_traits.h>
#include <CGAL/AABB_tree.h>
#include <CGAL/Exact_predicates_inexact_constructions_kernel.h>
#include <CGAL/Side_of_triangle_mesh.h>
#include <CGAL/Surface_mesh.h>

#include <gtest/gtest.h>

#include <Eigen/Dense>

#include <array>
#include <cmath>
#include <cstdint>
#include <iostream>
#include <limits>
#include <map>
#include <numbers>
#include <random>
#include <stdexcept>
#include <string>
#include <utility>
#include <vector>

namespace {

using mpm::test::icosphere;

using mpmgeom::BoundaryGrid;
using mpmgeom::ClosedSurface;
using mpmgeom::LayerLocator;
using mpmgeom::TriangleMesh;

// ---------------------------------------------------------------------------------------------
// Layers built by hand

/// Smallest distance of xi to the faces of the reference cell (>= 0 inside).
double reference_margin(int dimension, const Eigen::Vector3d& xi) {
  if (dimension == 1) return std::min(xi[0], 1.0 - xi[0]);
  if (dimension == 2) return std::min({xi[0], 1.0 - xi[0], xi[1], 1.0 - xi[1]});
  return std::min({xi[0], xi[1], 1.0 - xi[0] - xi[1], xi[2], 1.0 - xi[2]});
}

/// A gently curved bowl, z = f(x, y), and its upward unit normal.
double bowl_height(double x, double y) {
  return 0.0375 * (x * x + y * y) + 0.05 * std::sin(2.0 * x) * std::cos(3.0 * y);
}
Eigen::Vector3d bowl_normal(double x, double y) {
  const double fx = 0.075 * x + 0.1 * std::cos(2.0 * x) * std::cos(3.0 * y);
  const double fy = 0.075 * y - 0.15 * std::sin(2.0 * x) * std::sin(3.0 * y);
  return Eigen::Vector3d(-fx, -fy, 1.0).normalized();
}

/// 3D: a ring 1 <= r <= 2 of the triangulated bowl, wedges extruded along the vertex normals by
/// `thickness` in `layers` sub-layers (node level k at k * thickness / layers). `flat`: the ring
/// on the plane z = 0.2 instead, extruded along +z (a wall over a plane: the wedges' maps are
/// affine, Newton converges in one step).
BoundaryGrid ring_layer(int radial, int around, int layers, double thickness, bool flat = false) {
  BoundaryGrid g;
  g.dimension = 3;
  g.layers = layers;
  g.thickness = thickness;
  const int wall_nodes = (radial + 1) * around;
  const auto id = [&](int i, int j) { return i * around + (j % around); };
  g.nodes.resize(static_cast<Eigen::Index>(wall_nodes) * (layers + 1), 3);
  g.node_normals.resize(g.nodes.rows(), 3);
  for (int level = 0; level <= layers; ++level) {
    for (int i = 0; i <= radial; ++i) {
      for (int j = 0; j < around; ++j) {
        const double r = 1.0 + static_cast<double>(i) / radial;
        const double theta = 2.0 * std::numbers::pi * j / around;
        const double x = r * std::cos(theta), y = r * std::sin(theta);
        const Eigen::Vector3d n = flat ? Eigen::Vector3d::UnitZ() : bowl_normal(x, y);
        const Eigen::Vector3d w(x, y, flat ? 0.2 : bowl_height(x, y));
        const Eigen::Index row = static_cast<Eigen::Index>(level) * wall_nodes + id(i, j);
        g.nodes.row(row) = (w + (thickness * level / layers) * n).transpose();
        g.node_normals.row(row) = n.transpose();
      }
    }
  }
  std::vector<std::array<int, 3>> triangles;  // counter-clockwise seen from above
  for (int i = 0; i < radial; ++i) {
    for (int j = 0; j < around; ++j) {
      const int a = id(i, j), b = id(i + 1, j), c = id(i + 1, j + 1), d = id(i, j + 1);
      triangles.push_back({a, b, c});
      triangles.push_back({a, c, d});
    }
  }
  const auto per_layer = static_cast<Eigen::Index>(triangles.size());
  g.cells.resize(per_layer * layers, 6);
  g.cell_layer.resize(g.cells.rows());
  g.cell_part = Eigen::VectorXi::Zero(g.cells.rows());
  g.part_names = {"bowl"};
  for (int level = 0; level < layers; ++level) {
    for (Eigen::Index t = 0; t < per_layer; ++t) {
      const Eigen::Index c = level * per_layer + t;
      for (int k = 0; k < 3; ++k) {
        g.cells(c, k) = level * wall_nodes + triangles[static_cast<std::size_t>(t)][k];
        g.cells(c, 3 + k) = (level + 1) * wall_nodes + triangles[static_cast<std::size_t>(t)][k];
      }
      g.cell_layer(c) = level;
    }
  }
  return g;
}

/// 2D: quads on the open polyline y = 0.3 sin(x), 0 <= x <= 4, material above (on the left).
BoundaryGrid strip_layer(int segments, int layers, double thickness) {
  BoundaryGrid g;
  g.dimension = 2;
  g.layers = layers;
  g.thickness = thickness;
  const int wall_nodes = segments + 1;
  g.nodes.resize(static_cast<Eigen::Index>(wall_nodes) * (layers + 1), 2);
  for (int level = 0; level <= layers; ++level) {
    for (int i = 0; i < wall_nodes; ++i) {
      const double x = 4.0 * i / segments;
      const Eigen::Vector2d tangent = Eigen::Vector2d(1.0, 0.3 * std::cos(x)).normalized();
      const Eigen::Vector2d normal(-tangent.y(), tangent.x());
      g.nodes.row(static_cast<Eigen::Index>(level) * wall_nodes + i) =
          (Eigen::Vector2d(x, 0.3 * std::sin(x)) + (thickness * level / layers) * normal)
              .transpose();
    }
  }
  g.cells.resize(static_cast<Eigen::Index>(segments) * layers, 4);
  g.cell_layer.resize(g.cells.rows());
  for (int level = 0; level < layers; ++level) {
    for (int i = 0; i < segments; ++i) {
      const Eigen::Index c = static_cast<Eigen::Index>(level) * segments + i;
      g.cells.row(c) << level * wall_nodes + i, level * wall_nodes + i + 1,
          (level + 1) * wall_nodes + i, (level + 1) * wall_nodes + i + 1;
      g.cell_layer(c) = level;
    }
  }
  return g;
}

/// 1D: wall at 0.3, material at x > 0.3, `layers` segments of total length `thickness`.
BoundaryGrid segment_layer(int layers, double thickness) {
  BoundaryGrid g;
  g.dimension = 1;
  g.layers = layers;
  g.thickness = thickness;
  g.nodes.resize(layers + 1, 1);
  for (int k = 0; k <= layers; ++k) g.nodes(k, 0) = 0.3 + thickness * k / layers;
  g.cells.resize(layers, 2);
  g.cell_layer.resize(layers);
  for (int k = 0; k < layers; ++k) {
    g.cells.row(k) << k, k + 1;
    g.cell_layer(k) = k;
  }
  return g;
}

/// Corner Jacobians of every cell are positive (the locator assumes a valid layer).
void expect_valid_layer(const BoundaryGrid& g) {
  std::vector<Eigen::Vector3d> corners;
  if (g.dimension == 1) corners = {{0, 0, 0}, {1, 0, 0}};
  if (g.dimension == 2) corners = {{0, 0, 0}, {1, 0, 0}, {0, 1, 0}, {1, 1, 0}};
  if (g.dimension == 3) {
    for (const double z : {0.0, 1.0}) {
      corners.insert(corners.end(), {{0, 0, z}, {1, 0, z}, {0, 1, z}});
    }
  }
  for (std::size_t c = 0; c < g.cell_count(); ++c) {
    for (const auto& xi : corners) {
      const Eigen::Matrix3d J = mpmgeom::cell_jacobian(g, c, xi);
      ASSERT_GT(J.topLeftCorner(g.dimension, g.dimension).determinant(), 0.0) << "cell " << c;
    }
  }
}

Eigen::Vector3d random_xi(int dimension, std::mt19937_64& rng) {
  std::uniform_real_distribution<double> u(0.0, 1.0);
  Eigen::Vector3d xi = Eigen::Vector3d::Zero();
  if (dimension == 1) {
    xi[0] = u(rng);
  } else if (dimension == 2) {
    xi[0] = u(rng);
    xi[1] = u(rng);
  } else {
    double r = u(rng), s = u(rng);
    if (r + s > 1.0) {
      r = 1.0 - r;
      s = 1.0 - s;
    }
    xi << r, s, u(rng);
  }
  return xi;
}

/// Maps random natural coordinates of random cells to points and locates them: the same cell
/// and xi within 1e-9, or (for points on a shared face only) a neighbour that maps to the same
/// point.
void expect_round_trip(const BoundaryGrid& g, int samples, std::uint64_t seed) {
  const LayerLocator locator(g);
  std::mt19937_64 rng(seed);
  std::uniform_int_distribution<std::size_t> pick(0, g.cell_count() - 1);
  const double scale = g.nodes.cwiseAbs().maxCoeff();
  int same = 0, neighbour = 0;
  Eigen::MatrixXd points(samples, g.dimension);
  std::vector<int> expected_cell(static_cast<std::size_t>(samples));
  for (int n = 0; n < samples; ++n) {
    const std::size_t c = pick(rng);
    const Eigen::Vector3d xi = random_xi(g.dimension, rng);
    const Eigen::Vector3d p = mpmgeom::cell_point(g, c, xi);
    points.row(n) = p.head(g.dimension).transpose();
    // The map in closed form (which Newton evaluates) is the basis's map: x and dx/dxi agree
    // to round-off of the coordinates.
    const Eigen::Matrix3d J = mpmgeom::cell_jacobian(g, c, xi);
    double r[3];
    double closed[3][3];
    const double origin[3] = {};
    mpmgeom::cell_map(g, c).evaluate(xi.data(), origin, r, closed);
    for (int i = 0; i < 3; ++i) {
      ASSERT_NEAR(r[i], p[i], 1e-14 * scale) << "cell " << c << " axis " << i;
      for (int j = 0; j < 3; ++j) {
        ASSERT_NEAR(closed[i][j], J(i, j), 1e-14 * scale) << "cell " << c << " (" << i << j << ")";
      }
    }
    const LayerLocator::Location loc = locator.locate(p);
    expected_cell[static_cast<std::size_t>(n)] = loc.cell;
    ASSERT_GE(loc.cell, 0) << "sample " << n << " cell " << c;
    // A hint (the cell of the step before) changes nothing, right, wrong or out of range.
    for (const int hint :
         {static_cast<int>(c), static_cast<int>(pick(rng)), -1, static_cast<int>(g.cell_count())}) {
      const LayerLocator::Location hinted = locator.locate(p, hint);
      EXPECT_EQ(hinted.cell, loc.cell) << "sample " << n << " hint " << hint;
      EXPECT_EQ(hinted.xi, loc.xi) << "sample " << n << " hint " << hint;
      EXPECT_EQ(hinted.jacobian, loc.jacobian) << "sample " << n << " hint " << hint;
    }
    // The Jacobian handed back is the map's at the answer (the basis gradients' J).
    const Eigen::Matrix3d at_answer =
        mpmgeom::cell_jacobian(g, static_cast<std::size_t>(loc.cell), loc.xi);
    EXPECT_LT((loc.jacobian - at_answer).cwiseAbs().maxCoeff(), 1e-14 * scale) << "sample " << n;
    if (loc.cell == static_cast<int>(c)) {
      ++same;
      EXPECT_LT((loc.xi - xi).cwiseAbs().maxCoeff(), 1e-9) << "cell " << c;
    } else {
      ++neighbour;
      EXPECT_LT(reference_margin(g.dimension, xi), 1e-8) << "interior point in the wrong cell";
      EXPECT_GE(reference_margin(g.dimension, loc.xi), -1e-10);
      const Eigen::Vector3d q = mpmgeom::cell_point(g, static_cast<std::size_t>(loc.cell), loc.xi);
      EXPECT_LT((q - p).norm(), 1e-12 * scale);
    }
  }
  std::cout << "[ round trip " << g.dimension << "D ] " << same << " same cell, " << neighbour
            << " neighbour of " << samples << "\n";
  EXPECT_GE(same, samples - 2);
  // The batch interface gives the same answers as the single-point one.
  std::vector<LayerLocator::Location> batch;
  locator.locate(points, batch);
  ASSERT_EQ(batch.size(), static_cast<std::size_t>(samples));
  for (int n = 0; n < samples; ++n) {
    EXPECT_EQ(batch[static_cast<std::size_t>(n)].cell, expected_cell[static_cast<std::size_t>(n)]);
  }
}

TEST(Locator, RoundTrip3DWedges) {
  for (const int layers : {1, 3}) {
    const BoundaryGrid g = ring_layer(6, 48, layers, 0.12);
    expect_valid_layer(g);
    expect_round_trip(g, 20000, 11 + static_cast<std::uint64_t>(layers));
  }
}

TEST(Locator, RoundTrip3DWedgesOnAPlane) {
  for (const int layers : {1, 3}) {
    const BoundaryGrid g = ring_layer(6, 48, layers, 0.12, true);
    expect_valid_layer(g);
    expect_round_trip(g, 20000, 51 + static_cast<std::uint64_t>(layers));
  }
}

TEST(Locator, RoundTrip2DQuads) {
  for (const int layers : {1, 2}) {
    const BoundaryGrid g = strip_layer(40, layers, 0.15);
    expect_valid_layer(g);
    expect_round_trip(g, 10000, 21 + static_cast<std::uint64_t>(layers));
  }
}

TEST(Locator, RoundTrip1DSegments) {
  for (const int layers : {1, 4}) {
    const BoundaryGrid g = segment_layer(layers, 0.25);
    expect_round_trip(g, 2000, 31 + static_cast<std::uint64_t>(layers));
  }
}

// Embree works in float: a layer far from the origin (where one float step is ~1e-4 of a
// cell) must still be located to double precision.
TEST(Locator, RoundTripFarFromTheOrigin) {
  BoundaryGrid g = ring_layer(4, 32, 2, 0.1);
  g.nodes.rowwise() += Eigen::RowVector3d(2.0e3, -1.5e3, 7.0e2);
  expect_valid_layer(g);
  expect_round_trip(g, 5000, 41);
}

// Points exactly on faces (the wall, the interface, faces between sub-layers and between
// neighbouring columns, corners) are found, in a cell that maps back to them, and always the
// same one.
TEST(Locator, PointsOnSharedFacesBelongToOneCell) {
  const BoundaryGrid g = ring_layer(4, 32, 2, 0.1);
  const LayerLocator locator(g);
  const double scale = g.nodes.cwiseAbs().maxCoeff();
  std::mt19937_64 rng(5);
  std::uniform_real_distribution<double> u(0.0, 1.0);
  std::vector<Eigen::Vector3d> points;
  for (std::size_t c = 0; c < g.cell_count(); c += 3) {
    const double a = u(rng), b = u(rng) * (1.0 - a);
    for (const Eigen::Vector3d& xi :
         {Eigen::Vector3d(a, b, 0.0), Eigen::Vector3d(a, b, 1.0), Eigen::Vector3d(0.0, a, u(rng)),
          Eigen::Vector3d(a, 1.0 - a, u(rng)), Eigen::Vector3d(0.0, 0.0, u(rng)),
          Eigen::Vector3d(1, 0, 1)}) {
      points.push_back(mpmgeom::cell_point(g, c, xi));
    }
  }
  for (const Eigen::Vector3d& p : points) {
    const LayerLocator::Location first = locator.locate(p);
    ASSERT_GE(first.cell, 0);
    EXPECT_GE(reference_margin(3, first.xi), -1e-10);
    EXPECT_LT((mpmgeom::cell_point(g, static_cast<std::size_t>(first.cell), first.xi) - p).norm(),
              1e-12 * scale);
    const LayerLocator::Location again = locator.locate(p);
    EXPECT_EQ(again.cell, first.cell);
    EXPECT_EQ(again.xi, first.xi);
    // Hinted with a neighbour sharing the face: still the same cell (the point is not clearly
    // inside either, so the full query decides).
    for (const int hint : {first.cell - 1, first.cell + 1}) {
      const LayerLocator::Location hinted = locator.locate(p, hint);
      EXPECT_EQ(hinted.cell, first.cell);
      EXPECT_EQ(hinted.xi, first.xi);
    }
  }
  // 1D: the node between two segments goes to one of them (whichever it is deeper in after
  // round-off), with the matching coordinate.
  LayerLocator built(segment_layer(2, 0.2));
  const LayerLocator segments(std::move(built));  // movable: the Embree scene stays put
  const LayerLocator::Location middle = segments.locate(Eigen::Vector3d(0.4, 0.0, 0.0));
  ASSERT_TRUE(middle.cell == 0 || middle.cell == 1);
  EXPECT_NEAR(middle.xi[0], middle.cell == 0 ? 1.0 : 0.0, 1e-12);
  EXPECT_EQ(segments.locate(Eigen::Vector3d(0.4, 0.0, 0.0)).cell, middle.cell);
}

TEST(Locator, PointsOutsideTheLayerGiveNoCell) {
  const double t = 0.12;
  {  // 3D: just below the wall and above the interface, in the hole, beyond the rim, far away.
    const BoundaryGrid g = ring_layer(6, 48, 2, t);
    const LayerLocator locator(g);
    std::mt19937_64 rng(7);
    std::uniform_real_distribution<double> u(0.0, 1.0);
    const auto per_layer = g.cell_count() / 2;
    int outside = 0;
    for (std::size_t c = 0; c < per_layer; ++c) {
      Eigen::Vector3d xi = random_xi(3, rng);
      xi[2] = -0.02;  // 0.02 of a sub-layer below the wall
      EXPECT_EQ(locator.locate(mpmgeom::cell_point(g, c, xi)).cell, -1) << "cell " << c;
      xi[2] = 1.02;  // above the interface
      EXPECT_EQ(locator.locate(mpmgeom::cell_point(g, c + per_layer, xi)).cell, -1);
      outside += 2;
    }
    for (int n = 0; n < 500; ++n) {
      const double theta = 2.0 * std::numbers::pi * u(rng);
      for (const double r : {0.9 * u(rng), 2.1 + u(rng)}) {
        const double x = r * std::cos(theta), y = r * std::sin(theta);
        const Eigen::Vector3d p(x, y, bowl_height(x, y) + t * u(rng));
        EXPECT_EQ(locator.locate(p).cell, -1) << p.transpose();
        ++outside;
      }
    }
    EXPECT_EQ(locator.locate(Eigen::Vector3d(100.0, 0.0, 0.0)).cell, -1);
    EXPECT_EQ(locator.locate(Eigen::Vector3d(std::nan(""), 0.0, 0.0)).cell, -1);
    std::cout << "[ outside 3D ] " << outside << " points checked\n";
  }
  {  // 2D: below, above, before the first and after the last column.
    const BoundaryGrid g = strip_layer(40, 1, t);
    const LayerLocator locator(g);
    for (std::size_t c = 0; c < g.cell_count(); ++c) {
      for (const double s : {0.1, 0.5, 0.9}) {
        EXPECT_EQ(locator.locate(mpmgeom::cell_point(g, c, {s, -0.02, 0.0})).cell, -1);
        EXPECT_EQ(locator.locate(mpmgeom::cell_point(g, c, {s, 1.02, 0.0})).cell, -1);
      }
    }
    EXPECT_EQ(locator.locate(mpmgeom::cell_point(g, 0, {-0.02, 0.5, 0.0})).cell, -1);
    EXPECT_EQ(locator.locate(mpmgeom::cell_point(g, g.cell_count() - 1, {1.02, 0.5, 0.0})).cell,
              -1);
  }
  {  // 1D
    const LayerLocator locator(segment_layer(3, 0.25));
    for (const double x : {0.3 - 1e-6, 0.55 + 1e-6, -5.0, 7.0}) {
      EXPECT_EQ(locator.locate(Eigen::Vector3d(x, 0.0, 0.0)).cell, -1) << x;
    }
    EXPECT_EQ(locator.locate(Eigen::Vector3d(0.3, 0.0, 0.0)).cell, 0);
    EXPECT_EQ(locator.locate(Eigen::Vector3d(0.55, 0.0, 0.0)).cell, 2);
  }
}

TEST(Locator, SkipFlagsAreHonoured) {
  const BoundaryGrid g = ring_layer(4, 32, 1, 0.1);
  const LayerLocator locator(g);
  std::mt19937_64 rng(9);
  std::uniform_int_distribution<std::size_t> pick(0, g.cell_count() - 1);
  const int count = 3000;
  Eigen::MatrixXd points(count, 3);
  std::vector<std::uint8_t> skip(count, 0);
  for (int n = 0; n < count; ++n) {
    points.row(n) = mpmgeom::cell_point(g, pick(rng), random_xi(3, rng)).transpose();
    skip[static_cast<std::size_t>(n)] = n % 3 == 0 ? 1 : 0;
  }
  std::vector<LayerLocator::Location> out;
  locator.locate(points, out, &skip);
  ASSERT_EQ(out.size(), static_cast<std::size_t>(count));
  for (int n = 0; n < count; ++n) {
    const auto& loc = out[static_cast<std::size_t>(n)];
    if (skip[static_cast<std::size_t>(n)] != 0) {
      EXPECT_EQ(loc.cell, -1);
    } else {
      EXPECT_EQ(loc.cell, locator.locate(points.row(n).transpose()).cell);
      EXPECT_GE(loc.cell, 0);
    }
  }
  std::vector<std::uint8_t> wrong_size(count - 1, 0);
  EXPECT_THROW(locator.locate(points, out, &wrong_size), std::invalid_argument);
  EXPECT_THROW(locator.locate(Eigen::MatrixXd::Zero(4, 2), out), std::invalid_argument);
}

// prefetch() is a hint to the memory system: any cell number, in range or not, leaves every
// answer as it was (the solver issues it for the hinted cells of the particles ahead).
TEST(Locator, PrefetchChangesNoAnswerAndIgnoresCellsOutOfRange) {
  const BoundaryGrid g = ring_layer(4, 32, 2, 0.1, true);
  const LayerLocator locator(g);
  std::mt19937_64 rng(17);
  std::uniform_int_distribution<std::size_t> pick(0, g.cell_count() - 1);
  const auto cells = static_cast<int>(g.cell_count());
  for (int n = 0; n < 500; ++n) {
    const auto c = static_cast<int>(pick(rng));
    const Eigen::Vector3d p =
        mpmgeom::cell_point(g, static_cast<std::size_t>(c), random_xi(3, rng));
    const LayerLocator::Location before = locator.locate(p, c);
    for (const int cell : {c, -1, cells, cells + 1000, std::numeric_limits<int>::min()}) {
      locator.prefetch(cell);
    }
    const LayerLocator::Location after = locator.locate(p, c);
    EXPECT_EQ(after.cell, before.cell);
    EXPECT_EQ(after.xi, before.xi);
    EXPECT_EQ(after.jacobian, before.jacobian);
  }
}

TEST(Locator, RejectsInconsistentGrids) {
  BoundaryGrid g = segment_layer(2, 0.2);
  g.cells(1, 1) = 7;
  EXPECT_THROW(LayerLocator{g}, std::invalid_argument);
  BoundaryGrid empty;
  empty.dimension = 2;
  empty.nodes.resize(0, 2);
  empty.cells.resize(0, 4);
  const LayerLocator none(empty);
  EXPECT_EQ(none.locate(Eigen::Vector3d::Zero()).cell, -1);
}

// ---------------------------------------------------------------------------------------------
// Closed surfaces built by hand

/// Builds a mesh from faces given by vertex positions, welding identical positions.
class MeshBuilder {
 public:
  int vertex(const Eigen::Vector3d& x) {
    const auto key = std::array<double, 3>{x[0], x[1], x[2]};
    const auto [it, inserted] = index_.try_emplace(key, static_cast<int>(vertices_.size()));
    if (inserted) vertices_.push_back(x);
    return it->second;
  }
  void triangle(const Eigen::Vector3d& a, const Eigen::Vector3d& b, const Eigen::Vector3d& c) {
    faces_.push_back({vertex(a), vertex(b), vertex(c)});
  }
  [[nodiscard]] TriangleMesh mesh() const {
    TriangleMesh m;
    m.V.resize(static_cast<Eigen::Index>(vertices_.size()), 3);
    for (std::size_t v = 0; v < vertices_.size(); ++v) {
      m.V.row(static_cast<Eigen::Index>(v)) = vertices_[v].transpose();
    }
    m.F.resize(static_cast<Eigen::Index>(faces_.size()), 3);
    for (std::size_t f = 0; f < faces_.size(); ++f) {
      for (int k = 0; k < 3; ++k) m.F(static_cast<Eigen::Index>(f), k) = faces_[f][k];
    }
    m.part = Eigen::VectorXi::Zero(m.F.rows());
    m.part_names = {"shape"};
    return m;
  }

 private:
  std::map<std::array<double, 3>, int> index_;
  std::vector<Eigen::Vector3d> vertices_;
  std::vector<std::array<int, 3>> faces_;
};

/// Axis-aligned box [lo, hi], each face split into m x m squares of two triangles (so there
/// are many edges and vertices on the axes and grid lines), outward counter-clockwise.
TriangleMesh split_box(const Eigen::Vector3d& lo, const Eigen::Vector3d& hi, int m) {
  MeshBuilder b;
  for (int axis = 0; axis < 3; ++axis) {
    const int u = (axis + 1) % 3, v = (axis + 2) % 3;  // e_u x e_v = e_axis
    for (const int side : {0, 1}) {
      for (int i = 0; i < m; ++i) {
        for (int j = 0; j < m; ++j) {
          const auto corner = [&](int di, int dj) {
            Eigen::Vector3d x;
            x[axis] = side == 0 ? lo[axis] : hi[axis];
            x[u] = lo[u] + (hi[u] - lo[u]) * (i + di) / m;
            x[v] = lo[v] + (hi[v] - lo[v]) * (j + dj) / m;
            return x;
          };
          const Eigen::Vector3d p00 = corner(0, 0), p10 = corner(1, 0), p11 = corner(1, 1),
                                p01 = corner(0, 1);
          if (side == 1) {
            b.triangle(p00, p10, p11);
            b.triangle(p00, p11, p01);
          } else {
            b.triangle(p00, p11, p10);
            b.triangle(p00, p01, p11);
          }
        }
      }
    }
  }
  return b.mesh();
}

/// Closed cylinder of radius 1 around the z axis, -1 <= z <= 1, caps as fans around the axis.
TriangleMesh cylinder(int segments) {
  MeshBuilder b;
  const Eigen::Vector3d bottom(0, 0, -1), top(0, 0, 1);
  for (int k = 0; k < segments; ++k) {
    const double a0 = 2.0 * std::numbers::pi * k / segments;
    const double a1 = 2.0 * std::numbers::pi * (k + 1) / segments;
    const Eigen::Vector3d b0(std::cos(a0), std::sin(a0), -1), b1(std::cos(a1), std::sin(a1), -1);
    const Eigen::Vector3d t0(b0.x(), b0.y(), 1), t1(b1.x(), b1.y(), 1);
    b.triangle(b0, b1, t1);
    b.triangle(b0, t1, t0);
    b.triangle(top, t0, t1);
    b.triangle(bottom, b1, b0);
  }
  return b.mesh();
}

double enclosed_volume(const TriangleMesh& m) {
  double six_v = 0.0;
  for (Eigen::Index f = 0; f < m.F.rows(); ++f) {
    six_v += m.V.row(m.F(f, 0)).dot(m.V.row(m.F(f, 1)).cross(m.V.row(m.F(f, 2))));
  }
  return six_v / 6.0;
}

// CGAL reference
using Kernel = CGAL::Exact_predicates_inexact_constructions_kernel;
using Point = Kernel::Point_3;
using SurfaceMesh = CGAL::Surface_mesh<Point>;
using Primitive = CGAL::AABB_face_graph_triangle_primitive<SurfaceMesh>;
using Tree = CGAL::AABB_tree<CGAL::AABB_traits<Kernel, Primitive>>;

SurfaceMesh to_cgal(const TriangleMesh& m) {
  SurfaceMesh s;
  std::vector<SurfaceMesh::Vertex_index> v;
  for (Eigen::Index i = 0; i < m.V.rows(); ++i) {
    v.push_back(s.add_vertex(Point(m.V(i, 0), m.V(i, 1), m.V(i, 2))));
  }
  for (Eigen::Index f = 0; f < m.F.rows(); ++f) {
    s.add_face(v[static_cast<std::size_t>(m.F(f, 0))], v[static_cast<std::size_t>(m.F(f, 1))],
               v[static_cast<std::size_t>(m.F(f, 2))]);
  }
  return s;
}

struct Agreement {
  int compared = 0, agreed = 0, excluded = 0, inside = 0;
};

/// Compares ClosedSurface::inside (batch and single) with CGAL on `points`; points within 1e-9
/// of the surface are left out.
Agreement compare_with_cgal(const TriangleMesh& mesh, const std::vector<Eigen::Vector3d>& points) {
  const SurfaceMesh reference_mesh = to_cgal(mesh);
  const CGAL::Side_of_triangle_mesh<SurfaceMesh, Kernel> side(reference_mesh);
  Tree tree(faces(reference_mesh).first, faces(reference_mesh).second, reference_mesh);
  tree.accelerate_distance_queries();
  const ClosedSurface surface(mesh);
  Eigen::MatrixX3d batch(static_cast<Eigen::Index>(points.size()), 3);
  for (std::size_t i = 0; i < points.size(); ++i) {
    batch.row(static_cast<Eigen::Index>(i)) = points[i].transpose();
  }
  std::vector<std::uint8_t> flags;
  surface.inside(batch, flags);
  Agreement a;
  for (std::size_t i = 0; i < points.size(); ++i) {
    const Point p(points[i][0], points[i][1], points[i][2]);
    if (tree.squared_distance(p) <= 1e-18) {
      ++a.excluded;
      continue;
    }
    const bool expected = side(p) == CGAL::ON_BOUNDED_SIDE;
    ++a.compared;
    a.inside += expected ? 1 : 0;
    const bool got = flags[i] != 0;
    EXPECT_EQ(got, surface.inside(points[i])) << "batch and single disagree";
    if (got == expected) {
      ++a.agreed;
    } else {
      ADD_FAILURE() << "inside(" << points[i].transpose() << ") = " << got << ", CGAL says "
                    << expected;
    }
  }
  return a;
}

std::vector<Eigen::Vector3d> random_points_in_grown_box(const TriangleMesh& mesh, int count,
                                                        std::uint64_t seed) {
  const Eigen::Vector3d lo = mesh.V.colwise().minCoeff().transpose();
  const Eigen::Vector3d hi = mesh.V.colwise().maxCoeff().transpose();
  const Eigen::Vector3d grow = 0.05 * (hi - lo);  // 10% larger in total
  std::mt19937_64 rng(seed);
  std::uniform_real_distribution<double> u(0.0, 1.0);
  std::vector<Eigen::Vector3d> points(static_cast<std::size_t>(count));
  for (auto& p : points) {
    for (int i = 0; i < 3; ++i) p[i] = lo[i] - grow[i] + u(rng) * (hi[i] - lo[i] + 2 * grow[i]);
  }
  return points;
}

void report(const std::string& name, const Agreement& a) {
  std::cout << "[ inside vs CGAL ] " << name << ": " << a.agreed << "/" << a.compared << " agree ("
            << a.inside << " inside, " << a.excluded << " within 1e-9 left out)\n";
}

TEST(ClosedSurface, InsideAgreesWithCgalOnRandomPoints) {
  constexpr int kPoints = 100000;
  const std::vector<std::pair<std::string, TriangleMesh>> shapes = {
      {"cube", split_box({-1, -1, -1}, {1, 1, 1}, 1)},
      {"icosphere", icosphere(3)},
      {"cylinder", cylinder(48)}};
  std::uint64_t seed = 100;
  for (const auto& [name, mesh] : shapes) {
    ASSERT_GT(enclosed_volume(mesh), 0.0) << name << " must be oriented outward";
    const Agreement a = compare_with_cgal(mesh, random_points_in_grown_box(mesh, kPoints, ++seed));
    report(name, a);
    EXPECT_EQ(a.agreed, a.compared) << name;
    EXPECT_GT(a.inside, kPoints / 4) << name;
  }
}

// The same check for a sphere far from the origin (Embree's float frame is centred on the mesh).
TEST(ClosedSurface, InsideAgreesWithCgalFarFromTheOrigin) {
  TriangleMesh sphere = icosphere(3);
  sphere.V.rowwise() += Eigen::RowVector3d(-3.0e3, 1.2e3, 4.5e2);
  const Agreement a = compare_with_cgal(sphere, random_points_in_grown_box(sphere, 20000, 55));
  report("icosphere at (-3e3, 1.2e3, 4.5e2)", a);
  EXPECT_EQ(a.agreed, a.compared);
}

// A box whose faces are split into many triangles, queried on the axes, on the grid lines of
// the faces, and from points whose first ray goes exactly through a mesh vertex or along the
// middle of an edge: the parity test must notice the grazing ray and cast another.
TEST(ClosedSurface, InsideIsRobustToRaysThroughEdgesAndVertices) {
  const int m = 8;
  const TriangleMesh mesh = split_box({-1, -1, -1}, {1, 1, 1}, m);
  const ClosedSurface surface(mesh);
  std::vector<Eigen::Vector3d> points;
  for (int k = -12; k <= 12; ++k) {  // on the axes, inside and outside
    const double s = k / 10.0 + 0.013;
    points.emplace_back(s, 0, 0);
    points.emplace_back(0, s, 0);
    points.emplace_back(0, 0, s);
  }
  for (int i = 0; i <= m; ++i) {  // on grid lines of the faces
    for (int j = 0; j <= m; ++j) {
      const double x = -1.0 + 2.0 * i / m, y = -1.0 + 2.0 * j / m;
      for (const double z : {-1.3, -0.5, 0.0, 0.7, 1.2}) {
        points.emplace_back(x, y, z);
        points.emplace_back(z, x, y);
        points.emplace_back(y, z, x);
      }
    }
  }
  // Aimed at vertices and edge midpoints along the first ray direction: from inside (behind
  // the face) and from outside (in front of it).
  const Eigen::Vector3d d0 = ClosedSurface::ray_direction(0);
  int aimed = 0;
  for (Eigen::Index f = 0; f < mesh.F.rows(); f += 3) {
    const Eigen::Vector3d a = mesh.V.row(mesh.F(f, 0)), b = mesh.V.row(mesh.F(f, 1));
    for (const Eigen::Vector3d& target : {a, Eigen::Vector3d(0.5 * (a + b))}) {
      for (const double back : {0.05, 0.4, 1.5, 3.0}) {
        points.push_back(target - back * d0);
        ++aimed;
      }
    }
  }
  int compared = 0, agreed = 0;
  for (const Eigen::Vector3d& p : points) {
    const double depth = 1.0 - p.cwiseAbs().maxCoeff();  // > 0 inside the box
    if (std::abs(depth) < 1e-9) continue;
    ++compared;
    const bool got = surface.inside(p);
    if (got == (depth > 0.0)) {
      ++agreed;
    } else {
      ADD_FAILURE() << "inside(" << p.transpose() << ") = " << got;
    }
  }
  std::cout << "[ edge-aimed box ] " << agreed << "/" << compared
            << " agree with the analytic box (" << aimed << " aimed at vertices and edges)\n";
  EXPECT_EQ(agreed, compared);
  // And the same points against CGAL, in the same box.
  const Agreement a = compare_with_cgal(mesh, points);
  report("split box, special points", a);
  EXPECT_EQ(a.agreed, a.compared);
}

TEST(ClosedSurface, SignedDistanceOfIcosphere) {
  const TriangleMesh mesh = icosphere(3);
  const ClosedSurface surface(mesh);
  const SurfaceMesh reference_mesh = to_cgal(mesh);
  const CGAL::Side_of_triangle_mesh<SurfaceMesh, Kernel> side(reference_mesh);
  // Brute force over all triangles, in the test (CGAL's exact closest-point on triangle).
  const auto brute_force = [&](const Eigen::Vector3d& p) {
    double best = std::numeric_limits<double>::infinity();
    const Point q(p[0], p[1], p[2]);
    for (Eigen::Index f = 0; f < mesh.F.rows(); ++f) {
      const auto vertex = [&](int k) {
        return Point(mesh.V(mesh.F(f, k), 0), mesh.V(mesh.F(f, k), 1), mesh.V(mesh.F(f, k), 2));
      };
      const Kernel::Triangle_3 t(vertex(0), vertex(1), vertex(2));
      best = std::min(best, std::sqrt(CGAL::to_double(CGAL::squared_distance(q, t))));
    }
    return best;
  };
  std::vector<Eigen::Vector3d> points = random_points_in_grown_box(mesh, 1500, 77);
  std::mt19937_64 rng(78);
  std::normal_distribution<double> gauss;
  for (int n = 0; n < 500; ++n) {  // close to the surface, both sides
    const Eigen::Vector3d dir = Eigen::Vector3d(gauss(rng), gauss(rng), gauss(rng)).normalized();
    points.push_back((1.0 + 0.02 * gauss(rng)) * dir);
  }
  points.emplace_back(0, 0, 0);
  points.emplace_back(3, -2, 5);
  double worst = 0.0;
  for (const Eigen::Vector3d& p : points) {
    const double expected = brute_force(p);
    const double sd = surface.signed_distance(p);
    worst = std::max(worst, std::abs(std::abs(sd) - expected));
    EXPECT_NEAR(std::abs(sd), expected, 1e-12) << p.transpose();
    EXPECT_NEAR(mpmgeom::distance_to_surface(mesh, p), expected, 1e-12);
    Eigen::Vector3d closest;
    EXPECT_NEAR(surface.distance(p, &closest), expected, 1e-12);
    EXPECT_NEAR((closest - p).norm(), expected, 1e-12);
    if (expected > 1e-9) {
      const bool inside = side(Point(p[0], p[1], p[2])) == CGAL::ON_BOUNDED_SIDE;
      EXPECT_EQ(sd < 0.0, inside) << p.transpose();
    }
  }
  std::cout << "[ signed distance ] " << points.size()
            << " points, largest |distance - brute force| = " << worst << "\n";
  // The centre is inside, at the inradius of the polyhedron (below 1, close to it).
  const double centre = surface.signed_distance(Eigen::Vector3d::Zero());
  EXPECT_LT(centre, -0.98);
  EXPECT_GT(centre, -1.0);
  const Eigen::Vector3d nan_point(std::nan(""), 0.0, 0.0);
  EXPECT_FALSE(surface.inside(nan_point));
  EXPECT_TRUE(std::isnan(surface.signed_distance(nan_point)));
}

TEST(ClosedSurface, DistanceToOpenSurface) {
  MeshBuilder b;  // the unit square in z = 0, two triangles, open
  b.triangle({0, 0, 0}, {1, 0, 0}, {1, 1, 0});
  b.triangle({0, 0, 0}, {1, 1, 0}, {0, 1, 0});
  const TriangleMesh square = b.mesh();
  const ClosedSurface surface(square);
  const std::vector<std::pair<Eigen::Vector3d, Eigen::Vector3d>> cases = {
      {{0.5, 0.25, 2.0}, {0.5, 0.25, 0.0}},
      {{2.0, 0.5, 0.0}, {1.0, 0.5, 0.0}},
      {{2.0, 2.0, 1.0}, {1.0, 1.0, 0.0}},
      {{-0.5, 0.3, -0.5}, {0.0, 0.3, 0.0}}};
  for (const auto& [p, expected_closest] : cases) {
    Eigen::Vector3d closest, closest_bvh;
    const double d = mpmgeom::distance_to_surface(square, p, &closest);
    EXPECT_NEAR(d, (p - expected_closest).norm(), 1e-14);
    EXPECT_LT((closest - expected_closest).norm(), 1e-14);
    EXPECT_NEAR(surface.distance(p, &closest_bvh), d, 1e-14);
    EXPECT_LT((closest_bvh - expected_closest).norm(), 1e-14);
  }
  TriangleMesh broken = square;
  broken.F(0, 2) = 9;
  EXPECT_THROW(ClosedSurface{broken}, std::invalid_argument);
  EXPECT_THROW(ClosedSurface{TriangleMesh{}}, std::invalid_argument);
}

TEST(ClosedSurface, FillSphereMatchesItsVolume) {
  const TriangleMesh sphere = icosphere(4);
  const double volume = enclosed_volume(sphere);
  const double h = 0.1;
  const int n = 2;
  const Eigen::MatrixX3d particles =
      mpmgeom::fill_closed_surface(sphere, Eigen::Vector3d(0.013, -0.021, 0.007), h, n);
  const double filled = static_cast<double>(particles.rows()) * std::pow(h / n, 3);
  std::cout << "[ fill sphere ] " << particles.rows() << " particles, volume " << filled << " vs "
            << volume << " (" << 100.0 * (filled / volume - 1.0) << " %)\n";
  EXPECT_NEAR(filled / volume, 1.0, 0.02);
  const ClosedSurface surface(sphere);
  for (Eigen::Index i = 0; i < particles.rows(); i += 97) {
    EXPECT_TRUE(surface.inside(particles.row(i).transpose()));
  }
}

TEST(ClosedSurface, FillGridAlignedBoxExactly) {
  // Box faces on grid planes (origin (0.1, -0.2, 0), h = 0.2): every sub-cell is wholly in or
  // out, so the count is exact.
  const Eigen::Vector3d origin(0.1, -0.2, 0.0);
  const double h = 0.2;
  const Eigen::Vector3d lo = origin + h * Eigen::Vector3d(1, -2, 0);
  const Eigen::Vector3d hi = origin + h * Eigen::Vector3d(7, 4, 4);
  const TriangleMesh box = split_box(lo, hi, 3);
  for (const int n : {1, 2, 3}) {
    const Eigen::MatrixX3d particles = mpmgeom::fill_closed_surface(box, origin, h, n);
    EXPECT_EQ(particles.rows(), 6 * 6 * 4 * n * n * n) << "n = " << n;
    for (Eigen::Index i = 0; i < particles.rows(); ++i) {
      for (int k = 0; k < 3; ++k) {
        ASSERT_GT(particles(i, k), lo[k]);
        ASSERT_LT(particles(i, k), hi[k]);
      }
    }
  }
  EXPECT_THROW(mpmgeom::fill_closed_surface(box, origin, 0.0, 2), std::invalid_argument);
  EXPECT_THROW(mpmgeom::fill_closed_surface(box, origin, h, 0), std::invalid_argument);
}

}  // namespace
