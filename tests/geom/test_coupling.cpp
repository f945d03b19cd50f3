// Coupling matrices R^A and R^alpha (mpmgeom::couple) and the layer-cell flags.
//
// Boundary grids are built by hand here (planar layers of wedges, straight quad layers, 1D
// segments), independent of the extrusion code. Exactness is checked three ways: identities
// that hold pointwise (partition of unity, linear and B-spline quadratic reproduction), hand
// computed entries on axis-aligned facets, and an independent reference (a conical-product
// Gauss rule on facets where N^A is one polynomial, and the refinement identity
// S_a^coarse = S_a^fine + (S_m1^fine + S_m2^fine) / 2 that exercises the cutting at knots).

#include "mpmgeom/coupling.hpp"

#include <gtest/gtest.h>

#include <algorithm>
#include <array>
#include <cmath>
#include <functional>
#include <random>
#include <stdexcept>
#include <vector>

#include <Eigen/Dense>
#include <Eigen/Geometry>

#include "mpmgeom/boundary_grid.hpp"
#include "mpmgeom/locator.hpp"

namespace {

using mpmgeom::BoundaryGrid;
using mpmgeom::couple;
using mpmgeom::Coupling;
using mpmgeom::CouplingSurface;
using mpmgeom::GridSpec;
using Kernel = GridSpec::Kernel;

constexpr std::array<Kernel, 2> kKernels{Kernel::linear, Kernel::bspline2};
constexpr std::array<CouplingSurface, 2> kSurfaces{CouplingSurface::interface,
                                                   CouplingSurface::wall};

// ---------------------------------------------------------------------------------------------
// Independent kernel and quadrature (written from the formulas, not from coupling.cpp).

/// 1D kernel N(d), d = node distance in grid units.
double kernel_1d(Kernel kernel, double d) {
  const double a = std::abs(d);
  if (kernel == Kernel::linear) return a < 1.0 ? 1.0 - a : 0.0;
  if (a <= 0.5) return 0.75 - a * a;
  if (a <= 1.5) return 0.5 * (1.5 - a) * (1.5 - a);
  return 0.0;
}

Eigen::Vector3i node_multi_index(const GridSpec& g, long linear) {
  Eigen::Vector3i i = Eigen::Vector3i::Zero();
  for (int d = g.dimension - 1; d >= 0; --d) {
    i[d] = static_cast<int>(linear % g.nodes[d]);
    linear /= g.nodes[d];
  }
  return i;
}

Eigen::Vector3d node_position(const GridSpec& g, long linear) {
  Eigen::Vector3d x = Eigen::Vector3d::Zero();
  const Eigen::Vector3i i = node_multi_index(g, linear);
  for (int d = 0; d < g.dimension; ++d) x[d] = g.origin[d] + g.spacing * i[d];
  return x;
}

double grid_basis(const GridSpec& g, long linear, const Eigen::Vector3d& x) {
  const Eigen::Vector3i i = node_multi_index(g, linear);
  double N = 1.0;
  for (int d = 0; d < g.dimension; ++d) {
    N *= kernel_1d(g.kernel, (x[d] - g.origin[d]) / g.spacing - i[d]);
  }
  return N;
}

/// n-point Gauss-Legendre on [0, 1] by Newton on P_n (exact to degree 2n - 1).
std::vector<std::array<double, 2>> gauss_legendre(int n) {
  std::vector<std::array<double, 2>> rule;
  for (int k = 1; k <= n; ++k) {
    double x = std::cos(M_PI * (k - 0.25) / (n + 0.5));
    double dp = 0.0;
    for (int it = 0; it < 100; ++it) {
      double p0 = 1.0, p1 = x;
      for (int m = 2; m <= n; ++m) {
        const double p2 = ((2.0 * m - 1.0) * x * p1 - (m - 1.0) * p0) / m;
        p0 = p1;
        p1 = p2;
      }
      dp = n * (x * p1 - p0) / (x * x - 1.0);
      const double dx = p1 / dp;
      x -= dx;
      if (std::abs(dx) < 1e-16) break;
    }
    rule.push_back({0.5 * (1.0 + x), 1.0 / ((1.0 - x * x) * dp * dp)});  // weight 2/(..)/2
  }
  return rule;
}

/// Integral over triangle (a, b, c) of f(x, barycentric), by the conical (Duffy) product of
/// 8-point Gauss-Legendre rules: x = a + u (b - a) + (1 - u) v (c - a), dA = 2A (1 - u) du dv.
/// Exact for polynomials of degree <= 14.
double reference_triangle_integral(
    const Eigen::Vector3d& a, const Eigen::Vector3d& b, const Eigen::Vector3d& c,
    const std::function<double(const Eigen::Vector3d&, const Eigen::Vector3d&)>& f) {
  static const auto rule = gauss_legendre(8);
  const double area = 0.5 * (b - a).cross(c - a).norm();
  double sum = 0.0;
  for (const auto& [u, wu] : rule) {
    for (const auto& [v, wv] : rule) {
      const Eigen::Vector3d bary(1.0 - u - (1.0 - u) * v, u, (1.0 - u) * v);
      const Eigen::Vector3d x = bary[0] * a + bary[1] * b + bary[2] * c;
      sum += wu * wv * 2.0 * area * (1.0 - u) * f(x, bary);
    }
  }
  return sum;
}

// ---------------------------------------------------------------------------------------------
// Hand-built boundary grids.

Eigen::Matrix3d random_rotation(std::mt19937& rng) {
  std::normal_distribution<double> n(0.0, 1.0);
  return Eigen::Quaterniond(n(rng), n(rng), n(rng), n(rng)).normalized().toRotationMatrix();
}

/// A square of side `side` centred at `center` in the plane spanned by frame.col(0), col(1),
/// split into n x n squares of two triangles each; wedges extruded by `thickness` along
/// frame.col(2). Nodes: the (n+1)^2 wall nodes, then the interface nodes in the same order.
BoundaryGrid planar_layer_3d(const Eigen::Vector3d& center, const Eigen::Matrix3d& frame,
                             double side, int n, double thickness) {
  BoundaryGrid b;
  b.dimension = 3;
  b.thickness = thickness;
  const int per_level = (n + 1) * (n + 1);
  const Eigen::Index node_total = 2 * static_cast<Eigen::Index>(per_level);
  b.nodes.resize(node_total, 3);
  b.node_normals.resize(node_total, 3);
  b.node_on_wall = Eigen::VectorXi::Zero(node_total);
  b.node_on_interface = Eigen::VectorXi::Zero(node_total);
  const auto id = [&](int i, int j) { return i * (n + 1) + j; };
  for (int i = 0; i <= n; ++i) {
    for (int j = 0; j <= n; ++j) {
      const Eigen::Vector3d p = center + frame.col(0) * side * (double(i) / n - 0.5) +
                                frame.col(1) * side * (double(j) / n - 0.5);
      b.nodes.row(id(i, j)) = p.transpose();
      b.nodes.row(per_level + id(i, j)) = (p + thickness * frame.col(2)).transpose();
      b.node_normals.row(id(i, j)) = frame.col(2).transpose();
      b.node_normals.row(per_level + id(i, j)) = frame.col(2).transpose();
      b.node_on_wall[id(i, j)] = 1;
      b.node_on_interface[per_level + id(i, j)] = 1;
    }
  }
  const Eigen::Index facet_total = 2 * static_cast<Eigen::Index>(n) * n;
  b.cells.resize(facet_total, 6);
  b.wall_facets.resize(facet_total, 3);
  b.interface_facets.resize(facet_total, 3);
  int t = 0;
  for (int i = 0; i < n; ++i) {
    for (int j = 0; j < n; ++j) {
      // counter-clockwise seen from +frame.col(2), the material side
      const std::array<std::array<int, 3>, 2> tris{
          {{id(i, j), id(i + 1, j), id(i + 1, j + 1)}, {id(i, j), id(i + 1, j + 1), id(i, j + 1)}}};
      for (const auto& tri : tris) {
        for (int k = 0; k < 3; ++k) {
          b.cells(t, k) = tri[k];
          b.cells(t, 3 + k) = per_level + tri[k];
          b.wall_facets(t, k) = tri[k];
          b.interface_facets(t, k) = per_level + tri[k];
        }
        ++t;
      }
    }
  }
  b.cell_layer = Eigen::VectorXi::Zero(t);
  b.cell_part = Eigen::VectorXi::Zero(t);
  b.wall_facet_part = Eigen::VectorXi::Zero(t);
  b.part_names = {"wall"};
  return b;
}

/// 2D: a polyline of `points` (#P x 2) with quads extruded by `thickness` along `normal`.
BoundaryGrid layer_2d(const Eigen::MatrixX2d& points, const Eigen::Vector2d& normal,
                      double thickness) {
  BoundaryGrid b;
  b.dimension = 2;
  b.thickness = thickness;
  const auto P = static_cast<int>(points.rows());
  const Eigen::Index node_total = 2 * static_cast<Eigen::Index>(P);
  b.nodes.resize(node_total, 2);
  b.node_normals.resize(node_total, 2);
  b.node_on_wall = Eigen::VectorXi::Zero(node_total);
  b.node_on_interface = Eigen::VectorXi::Zero(node_total);
  for (int i = 0; i < P; ++i) {
    b.nodes.row(i) = points.row(i);
    b.nodes.row(P + i) = points.row(i) + thickness * normal.transpose();
    b.node_normals.row(i) = normal.transpose();
    b.node_normals.row(P + i) = normal.transpose();
    b.node_on_wall[i] = 1;
    b.node_on_interface[P + i] = 1;
  }
  b.cells.resize(P - 1, 4);
  b.wall_facets.resize(P - 1, 2);
  b.interface_facets.resize(P - 1, 2);
  for (int i = 0; i + 1 < P; ++i) {
    b.cells.row(i) << i, i + 1, P + i, P + i + 1;
    b.wall_facets.row(i) << i, i + 1;
    b.interface_facets.row(i) << P + i, P + i + 1;
  }
  b.cell_layer = Eigen::VectorXi::Zero(P - 1);
  b.cell_part = Eigen::VectorXi::Zero(P - 1);
  b.wall_facet_part = Eigen::VectorXi::Zero(P - 1);
  b.part_names = {"wall"};
  return b;
}

BoundaryGrid layer_1d(double wall, double thickness) {
  BoundaryGrid b;
  b.dimension = 1;
  b.thickness = thickness;
  b.nodes.resize(2, 1);
  b.nodes << wall, wall + thickness;
  b.node_normals = Eigen::MatrixXd::Ones(2, 1);
  b.node_on_wall = Eigen::VectorXi::Zero(2);
  b.node_on_wall[0] = 1;
  b.node_on_interface = Eigen::VectorXi::Zero(2);
  b.node_on_interface[1] = 1;
  b.cells.resize(1, 2);
  b.cells << 0, 1;
  b.wall_facets.resize(1, 1);
  b.wall_facets << 0;
  b.interface_facets.resize(1, 1);
  b.interface_facets << 1;
  b.cell_layer = Eigen::VectorXi::Zero(1);
  b.cell_part = Eigen::VectorXi::Zero(1);
  b.wall_facet_part = Eigen::VectorXi::Zero(1);
  b.part_names = {"wall"};
  return b;
}

/// Only nodes and interface facets: enough for couple().
BoundaryGrid facets_only(const Eigen::MatrixXd& nodes, const Eigen::MatrixXi& facets) {
  BoundaryGrid b;
  b.dimension = static_cast<int>(nodes.cols());
  b.nodes = nodes;
  b.interface_facets = facets;
  b.wall_facets = facets;
  return b;
}

GridSpec make_grid(int dimension, Kernel kernel) {
  GridSpec g;
  g.dimension = dimension;
  g.origin = Eigen::Vector3d(-0.37, 0.21, -0.55);
  g.spacing = 0.25;
  g.nodes = Eigen::Vector3i::Ones();
  for (int d = 0; d < dimension; ++d) g.nodes[d] = 40;
  g.kernel = kernel;
  return g;
}

Eigen::Vector3d grid_centre(const GridSpec& g) {
  Eigen::Vector3d c = Eigen::Vector3d::Zero();
  for (int d = 0; d < g.dimension; ++d) c[d] = g.origin[d] + 0.5 * g.spacing * (g.nodes[d] - 1);
  return c;
}

/// Natural coordinates in the reference cell of a `dim`-D layer cell, uniform (the wedge's
/// triangle folded onto itself); samples 0-7 are the cell's corners (points on its boundary).
Eigen::Vector3d reference_point(int dim, int sample, std::mt19937& rng) {
  std::uniform_real_distribution<double> unit(0.0, 1.0);
  Eigen::Vector3d xi(unit(rng), unit(rng), unit(rng));
  if (dim == 3 && xi[0] + xi[1] > 1.0) {
    xi[0] = 1.0 - xi[0];
    xi[1] = 1.0 - xi[1];
  }
  if (sample < 8) {
    for (int d = 0; d < dim; ++d) xi[d] = (sample >> d) & 1;
    if (dim == 3 && xi[0] + xi[1] > 1.0) xi[1] = 0.0;
  }
  return xi;
}

int multiplier_at(const Coupling& c, int node) {
  const auto it = std::find(c.multiplier_node.begin(), c.multiplier_node.end(), node);
  EXPECT_NE(it, c.multiplier_node.end()) << "node " << node << " carries no multiplier";
  return static_cast<int>(it - c.multiplier_node.begin());
}

Eigen::Vector3d boundary_node(const BoundaryGrid& b, int node) {
  Eigen::Vector3d x = Eigen::Vector3d::Zero();
  x.head(b.dimension) = b.nodes.row(node).transpose();
  return x;
}

/// Exact integral S_mu and integral x S_mu per multiplier from the P1 formulas
/// (integral lambda_k = |T| / 3, integral x lambda_k = |T| / 12 (x_a + x_b + x_c + x_k)).
void surface_moments(const BoundaryGrid& b, const Coupling& c, const Eigen::MatrixXi& facets,
                     Eigen::VectorXd& integral, std::vector<Eigen::Vector3d>& first) {
  const auto M = static_cast<Eigen::Index>(c.multiplier_node.size());
  integral = Eigen::VectorXd::Zero(M);
  first.assign(static_cast<std::size_t>(M), Eigen::Vector3d::Zero());
  for (Eigen::Index f = 0; f < facets.rows(); ++f) {
    const int n = b.dimension;
    std::array<Eigen::Vector3d, 3> x;
    Eigen::Vector3d sum = Eigen::Vector3d::Zero();
    for (int k = 0; k < n; ++k) {
      x[k] = boundary_node(b, facets(f, k));
      sum += x[k];
    }
    for (int k = 0; k < n; ++k) {
      const int mu = multiplier_at(c, facets(f, k));
      if (n == 3) {
        const double area = 0.5 * (x[1] - x[0]).cross(x[2] - x[0]).norm();
        integral[mu] += area / 3.0;
        first[mu] += area / 12.0 * (sum + x[k]);
      } else if (n == 2) {
        const double length = (x[1] - x[0]).norm();
        integral[mu] += length / 2.0;
        first[mu] += length / 6.0 * (sum + x[k]);
      } else {
        integral[mu] += 1.0;
        first[mu] += x[k];
      }
    }
  }
}

/// Partition of unity of R^A and R^alpha, exact linear reproduction of R^A, non-negative
/// entries, and the multiplier integrals, for one coupling.
void check_consistency(const BoundaryGrid& b, const GridSpec& g, CouplingSurface surface) {
  const Coupling c = couple(b, g, surface);
  const Eigen::MatrixXi& facets =
      surface == CouplingSurface::interface ? b.interface_facets : b.wall_facets;
  ASSERT_EQ(c.grid.rows(), g.node_count());
  ASSERT_EQ(c.boundary.rows(), b.nodes.rows());
  ASSERT_EQ(c.grid.cols(), static_cast<Eigen::Index>(c.multiplier_node.size()));
  ASSERT_EQ(c.boundary.cols(), c.grid.cols());

  Eigen::VectorXd integral;
  std::vector<Eigen::Vector3d> first;
  surface_moments(b, c, facets, integral, first);
  const auto M = static_cast<Eigen::Index>(c.multiplier_node.size());
  Eigen::VectorXd grid_sum = Eigen::VectorXd::Zero(M), boundary_sum = Eigen::VectorXd::Zero(M);
  std::vector<Eigen::Vector3d> grid_first(static_cast<std::size_t>(M), Eigen::Vector3d::Zero());
  double min_entry = 0.0;
  for (int mu = 0; mu < c.grid.outerSize(); ++mu) {
    for (Eigen::SparseMatrix<double>::InnerIterator it(c.grid, mu); it; ++it) {
      grid_sum[mu] += it.value();
      grid_first[mu] += it.value() * node_position(g, it.row());
      min_entry = std::min(min_entry, it.value());
    }
    for (Eigen::SparseMatrix<double>::InnerIterator it(c.boundary, mu); it; ++it) {
      boundary_sum[mu] += it.value();
    }
  }
  const double extent = grid_centre(g).norm() + g.spacing * g.nodes.maxCoeff();
  for (Eigen::Index mu = 0; mu < M; ++mu) {
    const double tol = 1e-12 * integral[mu];
    EXPECT_NEAR(c.multiplier_integral[mu], integral[mu], tol);
    EXPECT_NEAR(grid_sum[mu], integral[mu], tol) << "partition of unity, multiplier " << mu;
    EXPECT_NEAR(boundary_sum[mu], integral[mu], tol) << "R^alpha columns, multiplier " << mu;
    for (int d = 0; d < g.dimension; ++d) {
      EXPECT_NEAR(grid_first[mu][d], first[mu][d], tol * extent)
          << "first moment, axis " << d << ", multiplier " << mu;
    }
  }
  EXPECT_GE(min_entry, -1e-15);
}

// ---------------------------------------------------------------------------------------------

TEST(Coupling, GridSpecIndexIsLastAxisFastest) {
  GridSpec g;
  g.dimension = 3;
  g.nodes = Eigen::Vector3i(4, 5, 6);
  EXPECT_EQ(g.node_count(), 120);
  EXPECT_EQ(g.linear_index(Eigen::Vector3i(1, 2, 3)), 1 * 30 + 2 * 6 + 3);
  EXPECT_EQ(g.linear_index(Eigen::Vector3i(3, 4, 5)), 119);
  g.dimension = 2;
  g.nodes = Eigen::Vector3i(4, 5, 1);
  EXPECT_EQ(g.node_count(), 20);
  EXPECT_EQ(g.linear_index(Eigen::Vector3i(2, 3, 0)), 2 * 5 + 3);
  g.dimension = 1;
  g.nodes = Eigen::Vector3i(7, 1, 1);
  EXPECT_EQ(g.node_count(), 7);
  EXPECT_EQ(g.linear_index(Eigen::Vector3i(6, 0, 0)), 6);
}

TEST(Coupling, PartitionOfUnityAndLinearReproduction3D) {
  std::mt19937 rng(7);
  std::uniform_real_distribution<double> shift(-1.0, 1.0), side(0.8, 3.0);
  for (const Kernel kernel : kKernels) {
    const GridSpec g = make_grid(3, kernel);
    for (int trial = 0; trial < 8; ++trial) {
      const Eigen::Vector3d centre =
          grid_centre(g) + Eigen::Vector3d(shift(rng), shift(rng), shift(rng));
      const BoundaryGrid b =
          planar_layer_3d(centre, random_rotation(rng), side(rng), 1 + trial % 4, g.spacing);
      for (const CouplingSurface surface : kSurfaces) {
        SCOPED_TRACE(testing::Message() << "kernel " << int(kernel) << " trial " << trial
                                        << " surface " << int(surface));
        check_consistency(b, g, surface);
      }
    }
  }
}

TEST(Coupling, PartitionOfUnityAndLinearReproduction2D) {
  std::mt19937 rng(11);
  std::uniform_real_distribution<double> shift(-1.0, 1.0), angle(0.0, 2.0 * M_PI);
  std::uniform_real_distribution<double> step(0.05, 0.7), jitter(-0.2, 0.2);
  for (const Kernel kernel : kKernels) {
    const GridSpec g = make_grid(2, kernel);
    for (int trial = 0; trial < 10; ++trial) {
      const double phi = angle(rng);
      const Eigen::Vector2d along(std::cos(phi), std::sin(phi)), normal(-along.y(), along.x());
      Eigen::MatrixX2d points(6, 2);
      double s = 0.0;
      for (int i = 0; i < 6; ++i) {
        const Eigen::Vector2d p = grid_centre(g).head(2) + Eigen::Vector2d(shift(rng), 0.0) +
                                  s * along + jitter(rng) * normal;
        points.row(i) = p.transpose();
        s += step(rng);
      }
      const BoundaryGrid b = layer_2d(points, normal, g.spacing);
      for (const CouplingSurface surface : kSurfaces) {
        SCOPED_TRACE(testing::Message() << "kernel " << int(kernel) << " trial " << trial);
        check_consistency(b, g, surface);
      }
    }
  }
}

TEST(Coupling, OneDimensionalIsPointEvaluation) {
  std::mt19937 rng(3);
  std::uniform_real_distribution<double> position(1.0, 8.0);
  for (const Kernel kernel : kKernels) {
    const GridSpec g = make_grid(1, kernel);
    for (int trial = 0; trial < 20; ++trial) {
      const BoundaryGrid b = layer_1d(position(rng), 0.8 * g.spacing);
      check_consistency(b, g, CouplingSurface::wall);
      for (const CouplingSurface surface : kSurfaces) {
        const Coupling c = couple(b, g, surface);
        const int node = surface == CouplingSurface::wall ? 0 : 1;
        ASSERT_EQ(c.multiplier_node, std::vector<int>{node});
        EXPECT_EQ(c.multiplier_integral[0], 1.0);
        EXPECT_EQ(c.boundary.coeff(node, 0), 1.0);
        EXPECT_EQ(c.boundary.coeff(1 - node, 0), 0.0);
        const Eigen::Vector3d x(b.nodes(node, 0), 0.0, 0.0);
        for (long J = 0; J < g.node_count(); ++J) {
          EXPECT_NEAR(c.grid.coeff(J, 0), grid_basis(g, J, x), 1e-15) << "node " << J;
        }
      }
    }
  }
}

// An axis-aligned facet mesh on z = z0, grid origin 0, spacing h. On a facet in a plane z = z0
// the basis factorizes, N_J = N_i(x) N_j(y) N_k(z0), so with sum_mu S_mu = 1 on the square
// Q = [2h, 4h]^2:  sum_mu R^A_{J mu} = F_i F_j N_k(z0),  F_i = integral_{2h}^{4h} N_i(x) dx.
//   tent:      F_2 = F_4 = h/2, F_3 = h, others 0.
//   B-spline:  F_3 = h integral_{-1}^{1} N = h (1 - 2 integral_{1}^{3/2} (3/2 - d)^2 / 2) = 23h/24;
//              F_2 = F_4 = h integral_0^2 N = h/2;  F_1 = F_5 = h integral_1^3 N = h/48.
// N_k(z0): on a grid plane z0 = 3h: tent (0, 1, 0), B-spline (1/8, 3/4, 1/8) at k = 2, 3, 4;
//          off the planes z0 = 3.3h: tent 0.7 at k = 3, 0.3 at k = 4; B-spline 0.02, 0.66, 0.32.
TEST(Coupling, AxisAlignedSquareMatchesHandIntegrals) {
  const double h = 0.5;
  for (const Kernel kernel : kKernels) {
    GridSpec g;
    g.dimension = 3;
    g.spacing = h;
    g.nodes = Eigen::Vector3i::Constant(9);
    g.kernel = kernel;
    const bool tent = kernel == Kernel::linear;
    const auto F = [&](int i) {
      if (tent) return i == 3 ? h : (i == 2 || i == 4) ? h / 2 : 0.0;
      return i == 3               ? 23.0 * h / 24.0
             : (i == 2 || i == 4) ? h / 2
             : (i == 1 || i == 5) ? h / 48
                                  : 0.0;
    };
    for (const double z0 : {3.0, 3.3}) {
      const auto Nz = [&](int k) {
        if (z0 == 3.0)
          return tent ? (k == 3 ? 1.0 : 0.0) : (k == 3 ? 0.75 : (k == 2 || k == 4) ? 0.125 : 0.0);
        if (tent) return k == 3 ? 0.7 : k == 4 ? 0.3 : 0.0;
        return k == 2 ? 0.02 : k == 3 ? 0.66 : k == 4 ? 0.32 : 0.0;
      };
      // n = 2: a 2 x 2 triangulated square, diagonals crossing the grid and mid-planes.
      const BoundaryGrid b = planar_layer_3d(Eigen::Vector3d(3.0 * h, 3.0 * h, z0 * h),
                                             Eigen::Matrix3d::Identity(), 2.0 * h, 2, 0.3 * h);
      const Coupling c = couple(b, g, CouplingSurface::wall);
      const Eigen::VectorXd row_sums = c.grid * Eigen::VectorXd::Ones(c.grid.cols());
      for (int i = 0; i < 9; ++i) {
        for (int j = 0; j < 9; ++j) {
          for (int k = 0; k < 9; ++k) {
            const double expected = F(i) * F(j) * Nz(k);
            EXPECT_NEAR(row_sums[g.linear_index(Eigen::Vector3i(i, j, k))], expected, 1e-14)
                << "kernel " << int(kernel) << " z0 " << z0 << " node " << i << j << k;
          }
        }
      }
    }
  }
}

// Single entries on one right triangle T with legs h along x and y, z = z0, where N^A is one
// polynomial. u = (x - x0)/h, v = (y - y0)/h on the reference triangle, barycentrics
// L0 = 1 - u - v (vertex 0 at (x0, y0)), L1 = u, L2 = v, and
// integral_T u^a v^b = h^2 a! b! / (a + b + 2)!.
//  tent, (x0, y0) = (2h, 2h), so N_2(x) = 1 - u = L0 + L2, N_3(x) = u, N_2(y) = 1 - v = L0 + L1:
//    R_{(2,2,k), 0} = h^2 N_k(z0) integral (L0 + L2)(L0 + L1) L0 = (1/20 + 2/60 + 1/120) = 11/120
//    R_{(3,2,k), 0} = h^2 N_k(z0) integral L1 (L0 + L1) L0 = (2/120 + 2/120) = 1/30
//    R_{(3,3,k), 0} = h^2 N_k(z0) integral L0 L1 L2 = 1/120
//  B-spline, (x0, y0) = (2.5h, 2.5h) (mid-planes), N_3(x) = 3/4 - (u - 1/2)^2 = 1/2 + u - u^2,
//  N_4(x) = u^2 / 2; expanding the polynomials and integrating monomials term by term:
//    R_{(3,3,k), 0} = h^2 N_k(z0) integral (1/2 + u - u^2)(1/2 + v - v^2)(1 - u - v) = 59/840
//    R_{(3,3,k), 1} = h^2 N_k(z0) integral (1/2 + u - u^2)(1/2 + v - v^2) u         = 383/5040
//    R_{(4,3,k), 0} = h^2 N_k(z0) integral (u^2 / 2)(1/2 + v - v^2)(1 - u - v)      = 13/2520
TEST(Coupling, RightTriangleEntriesMatchHandIntegrals) {
  const double h = 0.5, z0 = 3.3;  // N_k(z0) as in AxisAlignedSquareMatchesHandIntegrals
  for (const Kernel kernel : kKernels) {
    GridSpec g;
    g.dimension = 3;
    g.spacing = h;
    g.nodes = Eigen::Vector3i::Constant(9);
    g.kernel = kernel;
    const bool tent = kernel == Kernel::linear;
    const double x0 = tent ? 2.0 : 2.5;
    Eigen::MatrixXd nodes(3, 3);
    nodes << x0 * h, x0 * h, z0 * h, (x0 + 1.0) * h, x0 * h, z0 * h, x0 * h, (x0 + 1.0) * h, z0 * h;
    Eigen::MatrixXi facets(1, 3);
    facets << 0, 1, 2;
    const Coupling c = couple(facets_only(nodes, facets), g, CouplingSurface::interface);
    const auto R = [&](int i, int j, int k, int mu) {
      return c.grid.coeff(g.linear_index(Eigen::Vector3i(i, j, k)), mu);
    };
    const double hh = h * h;
    for (const auto& [k, Nz] :
         tent ? std::vector<std::pair<int, double>>{{3, 0.7}, {4, 0.3}}
              : std::vector<std::pair<int, double>>{{2, 0.02}, {3, 0.66}, {4, 0.32}}) {
      if (tent) {
        EXPECT_NEAR(R(2, 2, k, 0), hh * Nz * 11.0 / 120.0, 1e-15);
        EXPECT_NEAR(R(3, 2, k, 0), hh * Nz / 30.0, 1e-15);
        EXPECT_NEAR(R(3, 3, k, 0), hh * Nz / 120.0, 1e-15);
      } else {
        EXPECT_NEAR(R(3, 3, k, 0), hh * Nz * 59.0 / 840.0, 1e-15);
        EXPECT_NEAR(R(3, 3, k, 1), hh * Nz * 383.0 / 5040.0, 1e-15);
        EXPECT_NEAR(R(4, 3, k, 0), hh * Nz * 13.0 / 2520.0, 1e-15);
      }
    }
  }
}

// A tilted triangle (3D) or segment (2D) inside one polynomial piece of N^A (one A-cell for the
// tent, one cell shifted by h/2 for the B-spline): every entry against an independent rule.
TEST(Coupling, EntriesMatchReferenceRuleInsideOnePiece) {
  std::mt19937 rng(5);
  std::uniform_real_distribution<double> inside(0.02, 0.98);
  for (const Kernel kernel : kKernels) {
    const GridSpec g = make_grid(3, kernel);
    const double offset = kernel == Kernel::linear ? 0.0 : 0.5;
    for (int trial = 0; trial < 5; ++trial) {
      Eigen::MatrixXd nodes(3, 3);
      for (int v = 0; v < 3; ++v) {
        for (int d = 0; d < 3; ++d) {
          nodes(v, d) = g.origin[d] + g.spacing * (17.0 + offset + inside(rng));
        }
      }
      Eigen::MatrixXi facets(1, 3);
      facets << 0, 1, 2;
      const Coupling c = couple(facets_only(nodes, facets), g, CouplingSurface::interface);
      const Eigen::Vector3d a = nodes.row(0), b = nodes.row(1), cc = nodes.row(2);
      const double scale = 0.5 * (b - a).cross(cc - a).norm();
      int checked = 0;
      for (long J = 0; J < g.node_count(); ++J) {
        const Eigen::Vector3i i = node_multi_index(g, J);
        if ((i.array() < 15).any() || (i.array() > 20).any()) continue;
        for (int mu = 0; mu < 3; ++mu) {
          const double expected = reference_triangle_integral(
              a, b, cc, [&](const Eigen::Vector3d& x, const Eigen::Vector3d& bary) {
                return grid_basis(g, J, x) * bary[mu];
              });
          EXPECT_NEAR(c.grid.coeff(J, mu), expected, 1e-14 * scale);
          checked += expected != 0.0;
        }
      }
      EXPECT_EQ(checked, (kernel == Kernel::linear ? 8 : 27) * 3);
    }
    // 2D: a tilted segment, against 8-point Gauss-Legendre (degree 15).
    const GridSpec g2 = make_grid(2, kernel);
    const auto rule = gauss_legendre(8);
    for (int trial = 0; trial < 5; ++trial) {
      Eigen::MatrixXd nodes(2, 2);
      for (int v = 0; v < 2; ++v) {
        for (int d = 0; d < 2; ++d) {
          nodes(v, d) = g2.origin[d] + g2.spacing * (17.0 + offset + inside(rng));
        }
      }
      Eigen::MatrixXi facets(1, 2);
      facets << 0, 1;
      const Coupling c = couple(facets_only(nodes, facets), g2, CouplingSurface::interface);
      const Eigen::Vector3d a(nodes(0, 0), nodes(0, 1), 0.0), b(nodes(1, 0), nodes(1, 1), 0.0);
      const double length = (b - a).norm();
      int checked = 0;
      for (long J = 0; J < g2.node_count(); ++J) {
        const Eigen::Vector3i i = node_multi_index(g2, J);
        if ((i.head(2).array() < 15).any() || (i.head(2).array() > 20).any()) continue;
        for (int mu = 0; mu < 2; ++mu) {
          double expected = 0.0;
          for (const auto& [t, w] : rule) {
            expected += w * length * grid_basis(g2, J, a + t * (b - a)) * (mu == 0 ? 1.0 - t : t);
          }
          EXPECT_NEAR(c.grid.coeff(J, mu), expected, 1e-14 * length);
          checked += expected != 0.0;
        }
      }
      EXPECT_EQ(checked, (kernel == Kernel::linear ? 4 : 9) * 2);
    }
  }
}

// The quadratic B-spline reproduces quadratics: sum_J N_J(x) X_J^2 = x^2 + h^2/4 per axis, so
// sum_J R^A_{J mu} prod_d X_{J,d}^2 = integral S_mu prod_d (x_d^2 + h^2/4), a degree-7
// integrand across many pieces of tilted facets.
TEST(Coupling, BSplineQuadraticReproductionIsExact) {
  std::mt19937 rng(13);
  std::uniform_real_distribution<double> shift(-1.0, 1.0);
  const GridSpec g = make_grid(3, Kernel::bspline2);
  const double q = 0.25 * g.spacing * g.spacing;
  for (int trial = 0; trial < 4; ++trial) {
    const BoundaryGrid b =
        planar_layer_3d(grid_centre(g) + Eigen::Vector3d(shift(rng), shift(rng), shift(rng)),
                        random_rotation(rng), 2.1, 3, g.spacing);
    const Coupling c = couple(b, g, CouplingSurface::interface);
    const auto M = static_cast<Eigen::Index>(c.multiplier_node.size());
    Eigen::VectorXd expected = Eigen::VectorXd::Zero(M);
    for (Eigen::Index f = 0; f < b.interface_facets.rows(); ++f) {
      const Eigen::Vector3d x0 = b.nodes.row(b.interface_facets(f, 0));
      const Eigen::Vector3d x1 = b.nodes.row(b.interface_facets(f, 1));
      const Eigen::Vector3d x2 = b.nodes.row(b.interface_facets(f, 2));
      for (int k = 0; k < 3; ++k) {
        const int mu = multiplier_at(c, b.interface_facets(f, k));
        expected[mu] += reference_triangle_integral(
            x0, x1, x2, [&](const Eigen::Vector3d& x, const Eigen::Vector3d& bary) {
              return bary[k] * (x[0] * x[0] + q) * (x[1] * x[1] + q) * (x[2] * x[2] + q);
            });
      }
    }
    Eigen::VectorXd moment = Eigen::VectorXd::Zero(M);
    for (int mu = 0; mu < c.grid.outerSize(); ++mu) {
      for (Eigen::SparseMatrix<double>::InnerIterator it(c.grid, mu); it; ++it) {
        const Eigen::Vector3d X = node_position(g, it.row());
        moment[mu] += it.value() * X.cwiseAbs2().prod();
      }
    }
    for (Eigen::Index mu = 0; mu < M; ++mu) {
      // The integrand is positive, so expected[mu] is its own scale.
      EXPECT_NEAR(moment[mu], expected[mu], 1e-12 * expected[mu]) << "multiplier " << mu;
    }
  }
}

// Refining the facet mesh by edge midpoints leaves the coarse hat functions representable:
// S_a^coarse = S_a^fine + (S_m1^fine + S_m2^fine) / 2 over the midpoints m1, m2 of the edges at
// a. Coarse and fine facets are cut along different pieces, so this checks the cutting.
TEST(Coupling, RefinementIdentityHolds) {
  std::mt19937 rng(17);
  std::uniform_real_distribution<double> shift(-1.2, 1.2);
  for (const Kernel kernel : kKernels) {
    // 3D: one tilted triangle over several cells, and its four children.
    {
      const GridSpec g = make_grid(3, kernel);
      for (int trial = 0; trial < 4; ++trial) {
        Eigen::MatrixXd nodes(6, 3);
        for (int v = 0; v < 3; ++v) {
          nodes.row(v) =
              (grid_centre(g) + Eigen::Vector3d(shift(rng), shift(rng), shift(rng))).transpose();
        }
        nodes.row(3) = 0.5 * (nodes.row(0) + nodes.row(1));
        nodes.row(4) = 0.5 * (nodes.row(1) + nodes.row(2));
        nodes.row(5) = 0.5 * (nodes.row(2) + nodes.row(0));
        Eigen::MatrixXi coarse(1, 3), fine(4, 3);
        coarse << 0, 1, 2;
        fine << 0, 3, 5, 3, 1, 4, 5, 4, 2, 3, 4, 5;
        const Coupling cc = couple(facets_only(nodes, coarse), g, CouplingSurface::interface);
        const Coupling cf = couple(facets_only(nodes, fine), g, CouplingSurface::interface);
        ASSERT_EQ(cf.multiplier_node, (std::vector<int>{0, 1, 2, 3, 4, 5}));
        const std::array<std::array<int, 2>, 3> midpoints{{{3, 5}, {3, 4}, {4, 5}}};
        for (int a = 0; a < 3; ++a) {
          const Eigen::VectorXd coarse_col = cc.grid.col(a);
          const Eigen::VectorXd fine_col =
              cf.grid.col(a) + 0.5 * (cf.grid.col(midpoints[a][0]) + cf.grid.col(midpoints[a][1]));
          EXPECT_LE((coarse_col - fine_col).cwiseAbs().maxCoeff(),
                    1e-13 * coarse_col.cwiseAbs().maxCoeff())
              << "kernel " << int(kernel) << " trial " << trial << " vertex " << a;
        }
      }
    }
    // 2D: one tilted segment and its halves.
    {
      const GridSpec g = make_grid(2, kernel);
      for (int trial = 0; trial < 4; ++trial) {
        Eigen::MatrixXd nodes(3, 2);
        nodes.row(0) =
            (grid_centre(g).head(2) + Eigen::Vector2d(shift(rng), shift(rng))).transpose();
        nodes.row(1) =
            (grid_centre(g).head(2) + Eigen::Vector2d(shift(rng), shift(rng))).transpose();
        nodes.row(2) = 0.5 * (nodes.row(0) + nodes.row(1));
        Eigen::MatrixXi coarse(1, 2), fine(2, 2);
        coarse << 0, 1;
        fine << 0, 2, 2, 1;
        const Coupling cc = couple(facets_only(nodes, coarse), g, CouplingSurface::interface);
        const Coupling cf = couple(facets_only(nodes, fine), g, CouplingSurface::interface);
        for (int a = 0; a < 2; ++a) {
          const Eigen::VectorXd coarse_col = cc.grid.col(a);
          const Eigen::VectorXd fine_col = cf.grid.col(a) + 0.5 * cf.grid.col(2);
          EXPECT_LE((coarse_col - fine_col).cwiseAbs().maxCoeff(),
                    1e-13 * coarse_col.cwiseAbs().maxCoeff());
        }
      }
    }
  }
}

// R^alpha on a planar facet mesh is the P1 mass matrix |T|/12 [2 1 1; 1 2 1; 1 1 2] per
// triangle, and equals the integral of the wedges' own basis (alpha_basis on the face zeta = 1
// or 0) times S_mu, integrated independently.
TEST(Coupling, AlphaMatrixIsFacetMassMatrix) {
  std::mt19937 rng(19);
  const GridSpec g = make_grid(3, Kernel::bspline2);
  const BoundaryGrid b = planar_layer_3d(grid_centre(g), random_rotation(rng), 2.3, 3, 0.2);
  for (const CouplingSurface surface : kSurfaces) {
    const bool on_interface = surface == CouplingSurface::interface;
    const Eigen::MatrixXi& facets = on_interface ? b.interface_facets : b.wall_facets;
    const Coupling c = couple(b, g, surface);
    const Eigen::MatrixXd R = Eigen::MatrixXd(c.boundary);
    Eigen::MatrixXd mass = Eigen::MatrixXd::Zero(R.rows(), R.cols());
    Eigen::MatrixXd from_basis = Eigen::MatrixXd::Zero(R.rows(), R.cols());
    for (Eigen::Index f = 0; f < facets.rows(); ++f) {
      const Eigen::Vector3d x0 = b.nodes.row(facets(f, 0)), x1 = b.nodes.row(facets(f, 1)),
                            x2 = b.nodes.row(facets(f, 2));
      const double area = 0.5 * (x1 - x0).cross(x2 - x0).norm();
      for (int a = 0; a < 3; ++a) {
        for (int m = 0; m < 3; ++m) {
          const int mu = multiplier_at(c, facets(f, m));
          mass(facets(f, a), mu) += area / 12.0 * (a == m ? 2.0 : 1.0);
        }
      }
      // Facet f is the face zeta = 1 (interface) or 0 (wall) of wedge f, vertex k at
      // (r, s) = (0, 0), (1, 0), (0, 1).
      for (int m = 0; m < 3; ++m) {
        const int mu = multiplier_at(c, facets(f, m));
        for (int node = 0; node < 6; ++node) {
          from_basis(b.cells(f, node), mu) += reference_triangle_integral(
              x0, x1, x2, [&](const Eigen::Vector3d&, const Eigen::Vector3d& bary) {
                const Eigen::Vector3d xi(bary[1], bary[2], on_interface ? 1.0 : 0.0);
                return mpmgeom::alpha_basis(3, xi).N[node] * bary[m];
              });
        }
      }
    }
    EXPECT_LE((R - mass).cwiseAbs().maxCoeff(), 1e-15);
    EXPECT_LE((R - from_basis).cwiseAbs().maxCoeff(), 1e-14);
  }
}

TEST(Coupling, SurfaceOutsideTheGridThrows) {
  std::mt19937 rng(23);
  for (const Kernel kernel : kKernels) {
    const GridSpec g = make_grid(3, kernel);
    // A layer straddling the low-x face of the grid.
    const Eigen::Vector3d centre(g.origin.x(), grid_centre(g).y(), grid_centre(g).z());
    const BoundaryGrid b = planar_layer_3d(centre, random_rotation(rng), 1.0, 2, g.spacing);
    EXPECT_THROW((void)couple(b, g, CouplingSurface::wall), std::invalid_argument);
    EXPECT_THROW((void)couple(b, g, CouplingSurface::interface), std::invalid_argument);

    // 1D: the kernel support must have nodes; 0.3 h inside the first node is fine for the
    // tent only.
    const GridSpec g1 = make_grid(1, kernel);
    const BoundaryGrid near_edge = layer_1d(g1.origin.x() + 0.3 * g1.spacing, g1.spacing);
    if (kernel == Kernel::linear) {
      EXPECT_NO_THROW((void)couple(near_edge, g1, CouplingSurface::wall));
    } else {
      EXPECT_THROW((void)couple(near_edge, g1, CouplingSurface::wall), std::invalid_argument);
    }
    const BoundaryGrid beyond = layer_1d(g1.origin.x() + 40.0 * g1.spacing, g1.spacing);
    EXPECT_THROW((void)couple(beyond, g1, CouplingSurface::interface), std::invalid_argument);
  }
  // Dimension mismatch.
  EXPECT_THROW(
      (void)couple(layer_1d(1.0, 0.2), make_grid(2, Kernel::linear), CouplingSurface::wall),
      std::invalid_argument);
}

// The limits are inclusive: a tent surface lying in the grid's boundary plane is accepted and
// still a partition of unity (the nodes past the edge have weight 0).
TEST(Coupling, SurfaceOnTheGridBoundaryIsAccepted) {
  GridSpec g = make_grid(3, Kernel::linear);
  Eigen::Matrix3d frame = Eigen::Matrix3d::Identity();
  Eigen::Vector3d centre = grid_centre(g);
  centre.z() = g.origin.z() + g.spacing * (g.nodes.z() - 1);
  const BoundaryGrid top = planar_layer_3d(centre, frame, 1.3, 2, -g.spacing);
  check_consistency(top, g, CouplingSurface::wall);
  g.kernel = Kernel::bspline2;
  centre.z() = g.origin.z() + 0.5 * g.spacing;
  const BoundaryGrid bottom = planar_layer_3d(centre, frame, 1.3, 2, g.spacing);
  check_consistency(bottom, g, CouplingSurface::wall);
}

TEST(Coupling, LayerCellFlagsCoverTheLayer) {
  std::mt19937 rng(29);
  std::uniform_real_distribution<double> unit(0.0, 1.0);
  for (int dim = 1; dim <= 3; ++dim) {
    const GridSpec g = make_grid(dim, Kernel::bspline2);
    BoundaryGrid b;
    if (dim == 3) {
      b = planar_layer_3d(grid_centre(g), random_rotation(rng), 2.0, 4, 0.8 * g.spacing);
    } else if (dim == 2) {
      Eigen::MatrixX2d points(4, 2);
      points << 0.0, 0.0, 0.7, 0.3, 1.3, 0.2, 2.0, 0.9;
      points.rowwise() += grid_centre(g).head(2).transpose();
      b = layer_2d(points, Eigen::Vector2d(-0.3, 1.0).normalized(), 0.6 * g.spacing);
    } else {
      b = layer_1d(grid_centre(g).x() + 0.1, 1.7 * g.spacing);
    }
    const std::vector<std::uint8_t> flags = mpmgeom::layer_cell_flags(b, g);
    long cells = 1;
    for (int d = 0; d < dim; ++d) cells *= g.nodes[d] - 1;
    ASSERT_EQ(static_cast<long>(flags.size()), cells);
    const auto cell_of = [&](const Eigen::Vector3d& x) {
      long index = 0;
      for (int d = 0; d < dim; ++d) {
        const long i = static_cast<long>(std::floor((x[d] - g.origin[d]) / g.spacing));
        index = index * (g.nodes[d] - 1) + i;
      }
      return index;
    };
    for (std::size_t c = 0; c < b.cell_count(); ++c) {
      for (int sample = 0; sample < 200; ++sample) {
        const Eigen::Vector3d xi = reference_point(dim, sample, rng);
        const Eigen::Vector3d x = mpmgeom::cell_point(b, c, xi);
        EXPECT_EQ(flags[static_cast<std::size_t>(cell_of(x))], 1)
            << "dim " << dim << " cell " << c << " xi " << xi.transpose();
      }
    }
    const long flagged = std::count(flags.begin(), flags.end(), std::uint8_t{1});
    EXPECT_GT(flagged, 0);
    EXPECT_LT(flagged, cells / 10 + 8) << "flags far more cells than the layer touches";
    // A far cell: the grid's first corner.
    EXPECT_EQ(flags[0], 0);
  }
}

// LayerCellFilter flags the cells layer_cell_flags flags, keeps every point of the layer (every
// point of every cell, and every point the locator finds in a cloud over the flagged cells), and
// over a planar layer extruded along its normal (3D, 1D) keeps the points between its faces and
// drops those 1% of its thickness beyond either: the slab is the layer itself, grown only by the
// pads (1e-6 of a cell). (The 2D polyline's segments slope against its one extrusion direction:
// its slabs span the slope across a cell, and only the first checks apply.)
TEST(Coupling, LayerCellFilterKeepsTheLayerAndDropsWhatLiesBeyondItsFaces) {
  std::mt19937 rng(31);
  std::uniform_real_distribution<double> unit(0.0, 1.0);
  for (int variant = 1; variant <= 4; ++variant) {
    const bool warped = variant == 4;  // 3D, thickness varying over the layer: curved cells
    const int dim = warped ? 3 : variant;
    const GridSpec g = make_grid(dim, Kernel::bspline2);
    const double t = (dim == 1 ? 1.7 : dim == 2 ? 0.6 : 0.8) * g.spacing;
    BoundaryGrid b;
    Eigen::Vector3d normal = Eigen::Vector3d::UnitX();
    std::vector<Eigen::Vector3d> on_wall;  // points on a planar Gamma, inside its edges
    if (dim == 3) {
      const Eigen::Matrix3d frame = random_rotation(rng);
      b = planar_layer_3d(grid_centre(g), frame, 2.0, 4, t);
      normal = frame.col(2);
      for (int k = 0; k < 50; ++k) {
        on_wall.emplace_back(grid_centre(g) + 1.6 * (unit(rng) - 0.5) * frame.col(0) +
                             1.6 * (unit(rng) - 0.5) * frame.col(1));
      }
      if (warped) {
        const Eigen::Index half = b.nodes.rows() / 2;
        for (Eigen::Index n = half; n < b.nodes.rows(); ++n) {
          const Eigen::Vector3d wall = b.nodes.row(n - half).transpose();
          const double stretch = 1.0 + 0.4 * std::sin(3.0 * wall.x()) * std::cos(2.0 * wall.y());
          b.nodes.row(n) = (wall + stretch * t * normal).transpose();
        }
      }
    } else if (dim == 2) {
      Eigen::MatrixX2d points(4, 2);
      points << 0.0, 0.0, 0.7, 0.3, 1.3, 0.2, 2.0, 0.9;
      points.rowwise() += grid_centre(g).head(2).transpose();
      b = layer_2d(points, Eigen::Vector2d(-0.3, 1.0).normalized(), t);
    } else {
      b = layer_1d(grid_centre(g).x() + 0.1, t);
      on_wall.emplace_back(grid_centre(g).x() + 0.1, 0.0, 0.0);
    }
    const std::vector<std::uint8_t> flags = mpmgeom::layer_cell_flags(b, g);
    const mpmgeom::LayerCellFilter filter(b, g);
    const auto cell_of = [&](const Eigen::Vector3d& x) {
      Eigen::Vector3i i = Eigen::Vector3i::Zero();
      for (int a = 0; a < dim; ++a) {
        i[a] = static_cast<int>(std::floor((x[a] - g.origin[a]) / g.spacing));
      }
      return i;
    };
    Eigen::Vector3i cells = Eigen::Vector3i::Ones();
    for (int a = 0; a < dim; ++a) cells[a] = g.nodes[a] - 1;
    long differ = 0, flagged = 0;
    for (int i = 0; i < cells[0]; ++i) {
      for (int j = 0; j < cells[1]; ++j) {
        for (int k = 0; k < cells[2]; ++k) {
          const long index = (static_cast<long>(i) * cells[1] + j) * cells[2] + k;
          const bool flag = flags[static_cast<std::size_t>(index)] != 0;
          flagged += flag ? 1 : 0;
          if (filter.flagged(Eigen::Vector3i(i, j, k)) != flag) ++differ;
        }
      }
    }
    EXPECT_EQ(differ, 0) << "variant " << variant;
    EXPECT_EQ(static_cast<long>(filter.flagged_cells()), flagged);
    // Every point of every cell, its corners included.
    for (std::size_t c = 0; c < b.cell_count(); ++c) {
      for (int sample = 0; sample < 200; ++sample) {
        const Eigen::Vector3d xi = reference_point(dim, sample, rng);
        Eigen::Vector3d x = Eigen::Vector3d::Zero();
        x.head(dim) = mpmgeom::cell_point(b, c, xi).head(dim);
        EXPECT_TRUE(filter.may_hold(cell_of(x), x))
            << "variant " << variant << " cell " << c << " xi " << xi.transpose();
      }
    }
    // Every point the locator finds among random points around the layer.
    const mpmgeom::LayerLocator locator(b);
    Eigen::Vector3d lo = Eigen::Vector3d::Zero(), hi = Eigen::Vector3d::Zero();
    lo.head(dim) = b.nodes.colwise().minCoeff().transpose().array() - g.spacing;
    hi.head(dim) = b.nodes.colwise().maxCoeff().transpose().array() + g.spacing;
    int found = 0, kept = 0;
    for (int n = 0; n < 20000; ++n) {
      Eigen::Vector3d x = Eigen::Vector3d::Zero();
      for (int a = 0; a < dim; ++a) x[a] = lo[a] + (hi[a] - lo[a]) * unit(rng);
      const bool in_layer = locator.locate(x).cell >= 0;
      const bool may = filter.may_hold(cell_of(x), x);
      found += in_layer ? 1 : 0;
      kept += may ? 1 : 0;
      if (in_layer) {
        EXPECT_TRUE(may) << "variant " << variant << " x " << x.transpose();
      }
    }
    EXPECT_GT(found, 0);
    EXPECT_GE(kept, found);
    // Across the faces of a planar layer: 1% of t beyond either face is dropped.
    for (const Eigen::Vector3d& wall : warped ? std::vector<Eigen::Vector3d>{} : on_wall) {
      for (const double s : {-0.01, 0.01, 0.5, 0.99, 1.01}) {
        const Eigen::Vector3d x = wall + s * t * normal;
        EXPECT_EQ(filter.may_hold(cell_of(x), x), s > 0.0 && s < 1.0)
            << "variant " << variant << " at " << s << " of the thickness, x " << x.transpose();
      }
    }
  }
}

}  // namespace
