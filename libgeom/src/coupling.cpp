// Coupling matrices R^A and R^alpha (DESIGN.md sections 3.4 and 4), integrated exactly.
//
// On a facet of the coupling surface, N^A_J is piecewise polynomial: a tensor product of 1D
// kernels that change polynomial piece at the knots of each axis,
//   linear tent           : knots at grid planes      xg_d = k          (piece degree 1 per axis)
//   quadratic B-spline    : knots at cell mid-planes  xg_d = k + 1/2    (piece degree 2 per axis)
// with xg = (x - origin) / h. Each facet is cut along every knot plane it crosses, so that N^A_J
// is one polynomial on each piece, and each piece is integrated with a rule exact for the
// product N^A_J S_mu (S_mu is linear on the facet):
//
//   3D triangle: restricted to a plane, N^A_J has degree <= 3 (tent) or <= 6 (B-spline); with
//                S_mu the integrand has degree <= 4 or <= 7. Pieces are convex polygons (a
//                triangle clipped by axis-aligned planes), fan-triangulated, and each triangle
//                integrated with Dunavant's 16-point rule, exact to degree 8 (all points inside,
//                all weights positive).
//   2D segment : N^A_J has degree <= 2 or <= 4 along the segment; with S_mu <= 3 or <= 5.
//                Each piece uses 4-point Gauss-Legendre, exact to degree 7.
//   1D point   : R^A_J = N^A_J(x_wall), evaluated directly.
//
// R^alpha needs no quadrature: the alpha basis is linear on cell faces, so N^alpha_S restricted
// to a facet is the facet's own hat function and R^alpha is the facet mass matrix
// (P1: measure/12 (1 + delta_ab) on a triangle, measure/6 (1 + delta_ab) on a segment).

#include "mpmgeom/coupling.hpp"

#include <algorithm>
#include <array>
#include <cmath>
#include <limits>
#include <sstream>
#include <stdexcept>
#include <string>
#include <unordered_map>

namespace mpmgeom {

long GridSpec::node_count() const {
  long count = 1;
  for (int d = 0; d < dimension; ++d) count *= nodes[d];
  return count;
}

long GridSpec::linear_index(const Eigen::Vector3i& i) const {
  // Horner form of sum_d i_d stride_d with stride[D-1] = 1, stride[d] = stride[d+1] nodes[d+1].
  long index = 0;
  for (int d = 0; d < dimension; ++d) index = index * nodes[d] + i[d];
  return index;
}

namespace {

// ---------------------------------------------------------------------------------------------
// The A-grid kernel, exactly as libmpm evaluates it (mpm::LinearShape, mpm::BSpline2Shape).

struct AxisWeights {
  int base = 0;
  std::array<double, 3> w{};
};

int kernel_support(GridSpec::Kernel kernel) { return kernel == GridSpec::Kernel::linear ? 2 : 3; }

/// Grid coordinate of the knots of the 1D kernel pieces, modulo 1.
double knot_offset(GridSpec::Kernel kernel) {
  return kernel == GridSpec::Kernel::linear ? 0.0 : 0.5;
}

AxisWeights axis_weights(GridSpec::Kernel kernel, double xg) {
  AxisWeights a;
  if (kernel == GridSpec::Kernel::linear) {
    a.base = static_cast<int>(std::floor(xg));
    const double fx = xg - a.base;
    a.w = {1.0 - fx, fx, 0.0};
  } else {
    a.base = static_cast<int>(std::floor(xg - 0.5));
    const double fx = xg - a.base;  // in [0.5, 1.5)
    a.w = {0.5 * (1.5 - fx) * (1.5 - fx), 0.75 - (fx - 1.0) * (fx - 1.0),
           0.5 * (fx - 0.5) * (fx - 0.5)};
  }
  return a;
}

// ---------------------------------------------------------------------------------------------
// Quadrature rules.

struct TrianglePoint {
  double l0, l1, l2, w;  ///< barycentric coordinates, weight (sums to 1 over the rule)
};

/// Dunavant (1985) degree-8 rule, 16 points: centroid, three 3-point orbits (a, a, 1 - 2a) and
/// one 6-point orbit (a, b, 1 - a - b). Coefficients to 32 digits; weights normalised to 1.
std::array<TrianglePoint, 16> dunavant_degree8() {
  std::array<TrianglePoint, 16> rule{};
  int n = 0;
  rule[n++] = {1.0 / 3.0, 1.0 / 3.0, 1.0 / 3.0, 0.14431560767778716825109111048906};
  const auto orbit3 = [&](double a, double w) {
    const double b = 1.0 - 2.0 * a;
    rule[n++] = {a, a, b, w};
    rule[n++] = {a, b, a, w};
    rule[n++] = {b, a, a, w};
  };
  orbit3(0.45929258829272315602881551449417, 0.09509163426728462479389610438858);
  orbit3(0.17056930775176020662229350149146, 0.10321737053471825028179155029212);
  orbit3(0.05054722831703097545842355059660, 0.03245849762319808031092592834178);
  const double a = 0.26311282963463811342178578628464;
  const double b = 0.72849239295540428124100037917606;
  const double c = 1.0 - a - b;
  const double w = 0.02723031417443499426484469007390;
  rule[n++] = {a, b, c, w};
  rule[n++] = {a, c, b, w};
  rule[n++] = {b, a, c, w};
  rule[n++] = {b, c, a, w};
  rule[n++] = {c, a, b, w};
  rule[n++] = {c, b, a, w};
  return rule;
}

struct LinePoint {
  double t, w;  ///< position on [0, 1], weight (sums to 1)
};

/// 4-point Gauss-Legendre on [0, 1], exact to degree 7.
std::array<LinePoint, 4> gauss_legendre4() {
  const double inner = std::sqrt(3.0 / 7.0 - 2.0 / 7.0 * std::sqrt(6.0 / 5.0));
  const double outer = std::sqrt(3.0 / 7.0 + 2.0 / 7.0 * std::sqrt(6.0 / 5.0));
  const double w_inner = (18.0 + std::sqrt(30.0)) / 36.0;
  const double w_outer = (18.0 - std::sqrt(30.0)) / 36.0;
  return {{{0.5 * (1.0 - outer), 0.5 * w_outer},
           {0.5 * (1.0 - inner), 0.5 * w_inner},
           {0.5 * (1.0 + inner), 0.5 * w_inner},
           {0.5 * (1.0 + outer), 0.5 * w_outer}}};
}

// ---------------------------------------------------------------------------------------------
// Checks.

void check_grid(const GridSpec& grid) {
  std::ostringstream why;
  if (grid.dimension < 1 || grid.dimension > 3) {
    why << "grid dimension " << grid.dimension << " is not 1, 2 or 3";
  } else if (!(grid.spacing > 0.0) || !std::isfinite(grid.spacing)) {
    why << "grid spacing " << grid.spacing << " is not positive and finite";
  } else if (!grid.origin.head(grid.dimension).allFinite()) {
    why << "grid origin is not finite";
  } else {
    for (int d = 0; d < grid.dimension; ++d) {
      if (grid.nodes[d] < 1) {
        why << "grid has " << grid.nodes[d] << " nodes along axis " << d;
        break;
      }
    }
  }
  if (!why.str().empty()) throw std::invalid_argument("coupling: " + why.str());
}

/// The closed range of grid coordinates where the whole kernel support lies inside the grid:
/// [0, n-1] for the tent, [1/2, n-3/2] for the B-spline. At the ends the nodes that would fall
/// outside have weight exactly 0.
void check_inside(const GridSpec& grid, const Eigen::Vector3d& x, int node) {
  // Surfaces placed exactly on the limit should not fail on rounding.
  const double tolerance = 1e-12;
  const double margin = grid.kernel == GridSpec::Kernel::linear ? 0.0 : 0.5;
  for (int d = 0; d < grid.dimension; ++d) {
    const double xg = (x[d] - grid.origin[d]) / grid.spacing;
    const double lo = margin;
    const double hi = grid.nodes[d] - 1.0 - margin;
    if (!std::isfinite(xg) || xg < lo - tolerance || xg > hi + tolerance) {
      std::ostringstream why;
      why << "coupling: surface node " << node << " lies outside the grid along axis " << d
          << " (grid coordinate " << xg << ", the kernel support needs [" << lo << ", " << hi
          << "])";
      throw std::invalid_argument(why.str());
    }
  }
}

// ---------------------------------------------------------------------------------------------
// Integration of N^A_J S_mu over one facet.

/// One entry of a column of R^A under assembly.
struct ColumnEntry {
  int row;
  double value;
};

/// Sorts a column by row and sums the entries of equal rows.
void compact(std::vector<ColumnEntry>& column) {
  std::sort(column.begin(), column.end(),
            [](const ColumnEntry& a, const ColumnEntry& b) { return a.row < b.row; });
  std::size_t out = 0;
  for (std::size_t k = 0; k < column.size(); ++k) {
    if (out > 0 && column[out - 1].row == column[k].row) {
      column[out - 1].value += column[k].value;
    } else {
      column[out++] = column[k];
    }
  }
  column.resize(out);
}

/// Accumulates integral N^A_J S_k for the k = 0..facet_nodes-1 hat functions of one facet over
/// a dense box of A-nodes around the facet, then emits the nonzeros as triplets.
class FacetIntegral {
 public:
  explicit FacetIntegral(const GridSpec& grid) : grid_(grid) {}

  /// Sets the node box for a facet whose vertices are `corners` (dimension used entries).
  void reset(const Eigen::Vector3d* corners, int count) {
    facet_nodes_ = count;
    const double offset = knot_offset(grid_.kernel);
    const int support = kernel_support(grid_.kernel);
    for (int d = 0; d < 3; ++d) {
      if (d >= grid_.dimension) {
        lo_[d] = 0;
        extent_[d] = 1;
        continue;
      }
      double min_xg = corners[0][d], max_xg = corners[0][d];
      for (int k = 1; k < count; ++k) {
        min_xg = std::min(min_xg, corners[k][d]);
        max_xg = std::max(max_xg, corners[k][d]);
      }
      min_xg = (min_xg - grid_.origin[d]) / grid_.spacing;
      max_xg = (max_xg - grid_.origin[d]) / grid_.spacing;
      // One node of slack each side: a quadrature point rounded across a knot may pick the
      // neighbouring base (with a weight of the order of the rounding).
      const int lo = std::max(0, static_cast<int>(std::floor(min_xg - offset)) - 1);
      const int hi =
          std::min(grid_.nodes[d] - 1, static_cast<int>(std::floor(max_xg - offset)) + support);
      lo_[d] = lo;
      extent_[d] = std::max(0, hi - lo + 1);
    }
    values_.assign(static_cast<std::size_t>(extent_.prod()) * facet_nodes_, 0.0);
  }

  /// Adds weight * N^A_J(x) * S[k] for every A-node J of the stencil at x.
  void add_point(const Eigen::Vector3d& x, double weight, const double* S) {
    const int support = kernel_support(grid_.kernel);
    std::array<AxisWeights, 3> axis;
    std::array<int, 3> count{1, 1, 1};
    for (int d = 0; d < grid_.dimension; ++d) {
      axis[d] = axis_weights(grid_.kernel, (x[d] - grid_.origin[d]) / grid_.spacing);
      count[d] = support;
    }
    for (int d = grid_.dimension; d < 3; ++d) {
      axis[d].base = 0;
      axis[d].w = {1.0, 0.0, 0.0};
    }
    for (int i = 0; i < count[0]; ++i) {
      const int li = axis[0].base + i - lo_[0];
      if (li < 0 || li >= extent_[0]) continue;  // outside the grid: weight ~ rounding
      for (int j = 0; j < count[1]; ++j) {
        const int lj = axis[1].base + j - lo_[1];
        if (lj < 0 || lj >= extent_[1]) continue;
        const double wij = weight * axis[0].w[i] * axis[1].w[j];
        for (int k = 0; k < count[2]; ++k) {
          const int lk = axis[2].base + k - lo_[2];
          if (lk < 0 || lk >= extent_[2]) continue;
          const double wN = wij * axis[2].w[k];
          const std::size_t local =
              (static_cast<std::size_t>(li) * extent_[1] + lj) * extent_[2] + lk;
          double* out = &values_[local * facet_nodes_];
          for (int n = 0; n < facet_nodes_; ++n) out[n] += wN * S[n];
        }
      }
    }
  }

  /// Appends (A-node linear index, value) of the nonzero entries to the column of each facet
  /// node, columns[k].
  void emit(const int* columns, std::vector<std::vector<ColumnEntry>>& out) const {
    Eigen::Vector3i node;
    for (int i = 0; i < extent_[0]; ++i) {
      node[0] = lo_[0] + i;
      for (int j = 0; j < extent_[1]; ++j) {
        node[1] = lo_[1] + j;
        for (int k = 0; k < extent_[2]; ++k) {
          node[2] = lo_[2] + k;
          const std::size_t local = (static_cast<std::size_t>(i) * extent_[1] + j) * extent_[2] + k;
          const double* v = &values_[local * facet_nodes_];
          for (int n = 0; n < facet_nodes_; ++n) {
            if (v[n] != 0.0) {
              out[columns[n]].push_back({static_cast<int>(grid_.linear_index(node)), v[n]});
            }
          }
        }
      }
    }
  }

 private:
  const GridSpec& grid_;
  int facet_nodes_ = 0;
  Eigen::Vector3i lo_ = Eigen::Vector3i::Zero();
  Eigen::Vector3i extent_ = Eigen::Vector3i::Ones();
  std::vector<double> values_;
};

/// A vertex of a clipped piece of a triangle facet: position and barycentric coordinates in the
/// parent facet (which are the values of the facet's three hat functions S_k there).
struct PieceVertex {
  Eigen::Vector3d x;
  Eigen::Vector3d bary;
};
using Polygon = std::vector<PieceVertex>;

/// Splits a convex polygon by the plane xg_axis = knot into the parts below and above
/// (Sutherland-Hodgman against both half-spaces at once). Vertices on the plane go to both.
void split_polygon(const Polygon& polygon, const GridSpec& grid, int axis, double knot,
                   Polygon& below, Polygon& above) {
  below.clear();
  above.clear();
  const std::size_t n = polygon.size();
  for (std::size_t i = 0; i < n; ++i) {
    const PieceVertex& p = polygon[i];
    const PieceVertex& q = polygon[(i + 1) % n];
    const double sp = (p.x[axis] - grid.origin[axis]) / grid.spacing - knot;
    const double sq = (q.x[axis] - grid.origin[axis]) / grid.spacing - knot;
    if (sp <= 0.0) below.push_back(p);
    if (sp >= 0.0) above.push_back(p);
    if ((sp < 0.0 && sq > 0.0) || (sp > 0.0 && sq < 0.0)) {
      const double t = sp / (sp - sq);
      PieceVertex cut{p.x + t * (q.x - p.x), p.bary + t * (q.bary - p.bary)};
      cut.x[axis] = grid.origin[axis] + grid.spacing * knot;  // exactly on the plane
      below.push_back(cut);
      above.push_back(cut);
    }
  }
}

/// Cuts a triangle facet along every knot plane it crosses; the pieces are convex polygons on
/// which N^A_J is a single polynomial.
void cut_triangle(const std::array<PieceVertex, 3>& facet, const GridSpec& grid,
                  std::vector<Polygon>& pieces) {
  const double offset = knot_offset(grid.kernel);
  pieces.assign(1, Polygon(facet.begin(), facet.end()));
  std::vector<Polygon> next;
  Polygon below, above;
  for (int axis = 0; axis < 3; ++axis) {
    next.clear();
    for (Polygon& polygon : pieces) {
      double lo = INFINITY, hi = -INFINITY;
      for (const PieceVertex& v : polygon) {
        const double xg = (v.x[axis] - grid.origin[axis]) / grid.spacing;
        lo = std::min(lo, xg);
        hi = std::max(hi, xg);
      }
      // Knots k + offset strictly inside (lo, hi), in increasing order.
      Polygon rest = std::move(polygon);
      const auto first = static_cast<long>(std::floor(lo - offset)) + 1;
      for (long k = first; k + offset < hi; ++k) {
        const double knot = static_cast<double>(k) + offset;
        if (knot <= lo) continue;
        split_polygon(rest, grid, axis, knot, below, above);
        if (below.size() >= 3) next.push_back(below);
        rest = above;
      }
      if (rest.size() >= 3) next.push_back(std::move(rest));
    }
    pieces.swap(next);
  }
}

void integrate_triangle(const PieceVertex& a, const PieceVertex& b, const PieceVertex& c,
                        FacetIntegral& integral) {
  static const std::array<TrianglePoint, 16> rule = dunavant_degree8();
  const double area = 0.5 * (b.x - a.x).cross(c.x - a.x).norm();
  if (area == 0.0) return;
  for (const TrianglePoint& q : rule) {
    const Eigen::Vector3d x = q.l0 * a.x + q.l1 * b.x + q.l2 * c.x;
    const Eigen::Vector3d S = q.l0 * a.bary + q.l1 * b.bary + q.l2 * c.bary;
    integral.add_point(x, q.w * area, S.data());
  }
}

void integrate_facet_3d(const std::array<Eigen::Vector3d, 3>& corners, const GridSpec& grid,
                        FacetIntegral& integral, std::vector<Polygon>& pieces) {
  const std::array<PieceVertex, 3> facet{{{corners[0], Eigen::Vector3d::UnitX()},
                                          {corners[1], Eigen::Vector3d::UnitY()},
                                          {corners[2], Eigen::Vector3d::UnitZ()}}};
  cut_triangle(facet, grid, pieces);
  for (const Polygon& piece : pieces) {
    for (std::size_t k = 1; k + 1 < piece.size(); ++k) {
      integrate_triangle(piece[0], piece[k], piece[k + 1], integral);
    }
  }
}

void integrate_facet_2d(const std::array<Eigen::Vector3d, 2>& corners, const GridSpec& grid,
                        FacetIntegral& integral, std::vector<double>& breaks) {
  static const std::array<LinePoint, 4> rule = gauss_legendre4();
  const Eigen::Vector3d& a = corners[0];
  const Eigen::Vector3d& b = corners[1];
  const double length = (b - a).head(2).norm();
  if (length == 0.0) return;
  const double offset = knot_offset(grid.kernel);
  breaks.assign({0.0, 1.0});
  for (int axis = 0; axis < 2; ++axis) {
    const double ga = (a[axis] - grid.origin[axis]) / grid.spacing;
    const double gb = (b[axis] - grid.origin[axis]) / grid.spacing;
    const double lo = std::min(ga, gb), hi = std::max(ga, gb);
    const auto first = static_cast<long>(std::floor(lo - offset)) + 1;
    for (long k = first; k + offset < hi; ++k) {
      const double knot = static_cast<double>(k) + offset;
      if (knot > lo) breaks.push_back((knot - ga) / (gb - ga));
    }
  }
  std::sort(breaks.begin(), breaks.end());
  for (std::size_t p = 0; p + 1 < breaks.size(); ++p) {
    const double t0 = breaks[p], dt = breaks[p + 1] - breaks[p];
    if (!(dt > 0.0)) continue;
    for (const LinePoint& q : rule) {
      const double t = t0 + dt * q.t;
      const Eigen::Vector3d x = a + t * (b - a);
      const std::array<double, 2> S{1.0 - t, t};
      integral.add_point(x, q.w * dt * length, S.data());
    }
  }
}

}  // namespace

Coupling couple(const BoundaryGrid& boundary, const GridSpec& grid, CouplingSurface surface) {
  check_grid(grid);
  const int dim = grid.dimension;
  if (boundary.dimension != dim) {
    throw std::invalid_argument("coupling: boundary grid dimension " +
                                std::to_string(boundary.dimension) + " differs from grid " +
                                std::to_string(dim));
  }
  if (boundary.nodes.cols() != dim && boundary.nodes.rows() > 0) {
    throw std::invalid_argument("coupling: boundary nodes have " +
                                std::to_string(boundary.nodes.cols()) + " columns, expected " +
                                std::to_string(dim));
  }
  if (grid.node_count() > std::numeric_limits<int>::max()) {
    throw std::invalid_argument("coupling: grid of " + std::to_string(grid.node_count()) +
                                " nodes exceeds the sparse matrix index range");
  }
  const Eigen::MatrixXi& facets =
      surface == CouplingSurface::interface ? boundary.interface_facets : boundary.wall_facets;
  const int facet_nodes = dim;  // point, segment, triangle
  const auto node_total = static_cast<int>(boundary.nodes.rows());
  if (facets.rows() > 0 && facets.cols() != facet_nodes) {
    throw std::invalid_argument("coupling: facets have " + std::to_string(facets.cols()) +
                                " nodes, expected " + std::to_string(facet_nodes));
  }

  // Multipliers: the facet nodes, in increasing boundary-node order.
  Coupling coupling;
  std::vector<int> multiplier_of(static_cast<std::size_t>(node_total), -1);
  for (Eigen::Index f = 0; f < facets.rows(); ++f) {
    for (int k = 0; k < facet_nodes; ++k) {
      const int node = facets(f, k);
      if (node < 0 || node >= node_total) {
        throw std::invalid_argument("coupling: facet " + std::to_string(f) + " refers to node " +
                                    std::to_string(node) + " of " + std::to_string(node_total));
      }
      multiplier_of[node] = 0;
    }
  }
  for (int node = 0; node < node_total; ++node) {
    if (multiplier_of[node] == 0) {
      multiplier_of[node] = static_cast<int>(coupling.multiplier_node.size());
      coupling.multiplier_node.push_back(node);
    }
  }
  const auto multipliers = static_cast<int>(coupling.multiplier_node.size());
  coupling.multiplier_integral = Eigen::VectorXd::Zero(multipliers);

  const auto position = [&](int node) {
    Eigen::Vector3d x = Eigen::Vector3d::Zero();
    x.head(dim) = boundary.nodes.row(node).transpose();
    return x;
  };

  // R^A is built column by column (one column per multiplier) and stored directly in
  // compressed column form: setFromTriplets would allocate per-row arrays over the whole A-grid.
  // A column receives one copy of an entry from each facet around its multiplier (about six in
  // 3D); it is compacted whenever it doubles, which bounds memory to about twice the result.
  std::vector<std::vector<ColumnEntry>> grid_columns(static_cast<std::size_t>(multipliers));
  std::vector<std::size_t> compact_at(static_cast<std::size_t>(multipliers), 64);
  std::vector<Eigen::Triplet<double>> boundary_entries;
  boundary_entries.reserve(static_cast<std::size_t>(facets.rows()) * facet_nodes * facet_nodes);
  FacetIntegral integral(grid);
  std::vector<Polygon> pieces;
  std::vector<double> breaks;
  std::array<Eigen::Vector3d, 3> corners;
  std::array<int, 3> columns{};
  for (Eigen::Index f = 0; f < facets.rows(); ++f) {
    for (int k = 0; k < facet_nodes; ++k) {
      corners[k] = position(facets(f, k));
      columns[k] = multiplier_of[facets(f, k)];
      check_inside(grid, corners[k], facets(f, k));
    }

    // R^A.
    integral.reset(corners.data(), facet_nodes);
    double measure = 1.0;
    if (dim == 3) {
      measure = 0.5 * (corners[1] - corners[0]).cross(corners[2] - corners[0]).norm();
      integrate_facet_3d(corners, grid, integral, pieces);
    } else if (dim == 2) {
      measure = (corners[1] - corners[0]).norm();
      integrate_facet_2d({corners[0], corners[1]}, grid, integral, breaks);
    } else {
      const double S = 1.0;
      integral.add_point(corners[0], 1.0, &S);
    }
    integral.emit(columns.data(), grid_columns);
    for (int k = 0; k < facet_nodes; ++k) {
      std::vector<ColumnEntry>& column = grid_columns[columns[k]];
      if (column.size() >= compact_at[columns[k]]) {
        compact(column);
        compact_at[columns[k]] = 2 * column.size() + 64;
      }
    }

    // R^alpha: the P1 facet mass matrix (triangle: A/12 (1 + delta_ab); segment: L/6 (1 +
    // delta_ab); point: 1), and integral S_mu = measure / (facet nodes).
    for (int a = 0; a < facet_nodes; ++a) {
      coupling.multiplier_integral[columns[a]] += measure / facet_nodes;
      for (int b = 0; b < facet_nodes; ++b) {
        double m = 1.0;
        if (dim == 3) m = measure / 12.0 * (a == b ? 2.0 : 1.0);
        if (dim == 2) m = measure / 6.0 * (a == b ? 2.0 : 1.0);
        boundary_entries.emplace_back(facets(f, a), columns[b], m);
      }
    }
  }

  std::vector<int> outer(static_cast<std::size_t>(multipliers) + 1, 0);
  for (int mu = 0; mu < multipliers; ++mu) {
    compact(grid_columns[mu]);
    outer[mu + 1] = outer[mu] + static_cast<int>(grid_columns[mu].size());
  }
  std::vector<int> inner(static_cast<std::size_t>(outer.back()));
  std::vector<double> values(inner.size());
  for (int mu = 0; mu < multipliers; ++mu) {
    for (std::size_t k = 0; k < grid_columns[mu].size(); ++k) {
      inner[outer[mu] + k] = grid_columns[mu][k].row;
      values[outer[mu] + k] = grid_columns[mu][k].value;
    }
    std::vector<ColumnEntry>().swap(grid_columns[mu]);
  }
  coupling.grid = Eigen::Map<const Eigen::SparseMatrix<double>>(
      static_cast<Eigen::Index>(grid.node_count()), multipliers, outer.back(), outer.data(),
      inner.data(), values.data());
  coupling.boundary.resize(node_total, multipliers);
  coupling.boundary.setFromTriplets(boundary_entries.begin(), boundary_entries.end());
  return coupling;
}

namespace {

// Calls f(index, c) for every A-cell (`index` its linear index, last axis fastest) that the closed
// cell meets the bounding box, grown by 1e-9 h, of layer cell c's nodes; `cells` gets the A-cells
// per axis (unused axes 1). The checks and messages of layer_cell_flags ("what" names the caller).
template <class F>
void for_each_cell_meeting_the_layer(const BoundaryGrid& boundary, const GridSpec& grid,
                                     const char* what, Eigen::Vector3i& cells, F&& f) {
  check_grid(grid);
  const int dim = grid.dimension;
  if (boundary.dimension != dim) {
    throw std::invalid_argument(std::string(what) + ": boundary grid dimension " +
                                std::to_string(boundary.dimension) + " differs from grid " +
                                std::to_string(dim));
  }
  cells = Eigen::Vector3i::Ones();
  for (int d = 0; d < dim; ++d) cells[d] = std::max(0, grid.nodes[d] - 1);
  if (cells.prod() == 0) return;

  // Layer cells are convex combinations of their nodes (the alpha basis is non-negative and
  // sums to 1), so the nodes' bounding box contains the cell. The slack covers rounding in the
  // particle's position and in floor((x - origin) / h).
  const double slack = 1e-9;
  const int per_cell = boundary.nodes_per_cell();
  if (boundary.cells.rows() > 0 && boundary.cells.cols() != per_cell) {
    throw std::invalid_argument(std::string(what) + ": cells have " +
                                std::to_string(boundary.cells.cols()) + " nodes, expected " +
                                std::to_string(per_cell));
  }
  for (Eigen::Index c = 0; c < boundary.cells.rows(); ++c) {
    Eigen::Vector3i lo = Eigen::Vector3i::Zero(), hi = Eigen::Vector3i::Zero();
    bool overlaps = true;
    for (int d = 0; d < dim && overlaps; ++d) {
      double min_xg = INFINITY, max_xg = -INFINITY;
      for (int k = 0; k < per_cell; ++k) {
        const int node = boundary.cells(c, k);
        if (node < 0 || node >= boundary.nodes.rows()) {
          throw std::invalid_argument(std::string(what) + ": layer cell " + std::to_string(c) +
                                      " refers to node " + std::to_string(node));
        }
        const double xg = (boundary.nodes(node, d) - grid.origin[d]) / grid.spacing;
        min_xg = std::min(min_xg, xg);
        max_xg = std::max(max_xg, xg);
      }
      if (!std::isfinite(min_xg) || !std::isfinite(max_xg)) {
        throw std::invalid_argument(std::string(what) + ": layer cell " + std::to_string(c) +
                                    " has a non-finite node");
      }
      const double first = std::floor(min_xg - slack), last = std::floor(max_xg + slack);
      if (last < 0.0 || first > cells[d] - 1.0) overlaps = false;
      lo[d] = static_cast<int>(std::max(first, 0.0));
      hi[d] = static_cast<int>(std::min(last, cells[d] - 1.0));
    }
    if (!overlaps) continue;
    Eigen::Vector3i i;
    for (i[0] = lo[0]; i[0] <= hi[0]; ++i[0]) {
      for (i[1] = lo[1]; i[1] <= hi[1]; ++i[1]) {
        for (i[2] = lo[2]; i[2] <= hi[2]; ++i[2]) {
          f((static_cast<long>(i[0]) * cells[1] + i[1]) * cells[2] + i[2], c);
        }
      }
    }
  }
}

}  // namespace

std::vector<std::uint8_t> layer_cell_flags(const BoundaryGrid& boundary, const GridSpec& grid) {
  Eigen::Vector3i cells;
  std::vector<std::uint8_t> flags;
  for_each_cell_meeting_the_layer(boundary, grid, "layer_cell_flags", cells,
                                  [&](long index, Eigen::Index) {
                                    if (flags.empty())
                                      flags.assign(static_cast<std::size_t>(cells.prod()), 0);
                                    flags[static_cast<std::size_t>(index)] = 1;
                                  });
  flags.resize(static_cast<std::size_t>(cells.prod()), 0);
  return flags;
}

LayerCellFilter::LayerCellFilter(const BoundaryGrid& boundary, const GridSpec& grid) {
  dimension_ = grid.dimension;
  const int per_cell = boundary.nodes_per_cell();
  const int half = per_cell / 2;  // wall-side nodes first, their interface-side nodes after
  // The A-cells met, numbered as met; per A-cell the directions' sum, then the bounds.
  std::unordered_map<long, int> index;
  std::vector<Eigen::Vector3d> direction;
  Eigen::Vector3i cells;
  const auto node = [&](Eigen::Index c, int k) {
    Eigen::Vector3d x = Eigen::Vector3d::Zero();
    x.head(dimension_) = boundary.nodes.row(boundary.cells(c, k)).transpose();
    return x;
  };
  for_each_cell_meeting_the_layer(
      boundary, grid, "LayerCellFilter", cells, [&](long cell, Eigen::Index c) {
        const auto [it, added] = index.try_emplace(cell, static_cast<int>(bounds_.size()));
        if (added) {
          bounds_.emplace_back();
          Bounds& b = bounds_.back();
          b.lo.fill(INFINITY);
          b.hi.fill(-INFINITY);
          b.slab_lo = INFINITY;
          b.slab_hi = -INFINITY;
          direction.emplace_back(Eigen::Vector3d::Zero());
        }
        Eigen::Vector3d up = Eigen::Vector3d::Zero();
        for (int k = 0; k < half; ++k) up += node(c, half + k) - node(c, k);
        if (up.norm() > 0.0) direction[static_cast<std::size_t>(it->second)] += up.normalized();
      });
  // Each layer cell's pad: LayerLocator's (1e-6 of its size plus a few float steps of its
  // coordinates), which also covers the 1e-10 of a cell its natural coordinates may lie out.
  const auto pad_of = [&](Eigen::Index c) {
    Eigen::Vector3d lo = Eigen::Vector3d::Constant(INFINITY), hi = -lo;
    for (int k = 0; k < per_cell; ++k) {
      lo = lo.cwiseMin(node(c, k));
      hi = hi.cwiseMax(node(c, k));
    }
    const double scale = std::max(lo.cwiseAbs().maxCoeff(), hi.cwiseAbs().maxCoeff());
    return 1e-6 * (hi - lo).norm() + 8.0 * std::numeric_limits<float>::epsilon() * scale;
  };
  for (std::size_t b = 0; b < bounds_.size(); ++b) {
    const Eigen::Vector3d& sum = direction[b];
    // Directions that cancel (a layer folded around an edge inside the cell): the box alone.
    if (sum.norm() > 1e-3) {
      for (int d = 0; d < 3; ++d)
        bounds_[b].normal[static_cast<std::size_t>(d)] = sum.normalized()[d];
    }
  }
  for_each_cell_meeting_the_layer(boundary, grid, "LayerCellFilter", cells,
                                  [&](long cell, Eigen::Index c) {
                                    Bounds& b = bounds_[static_cast<std::size_t>(index.at(cell))];
                                    const double pad = pad_of(c);
                                    const Eigen::Vector3d n(b.normal[0], b.normal[1], b.normal[2]);
                                    for (int k = 0; k < per_cell; ++k) {
                                      const Eigen::Vector3d x = node(c, k);
                                      for (int d = 0; d < dimension_; ++d) {
                                        const auto u = static_cast<std::size_t>(d);
                                        b.lo[u] = std::min(b.lo[u], x[d] - pad);
                                        b.hi[u] = std::max(b.hi[u], x[d] + pad);
                                      }
                                      b.slab_lo = std::min(b.slab_lo, n.dot(x) - pad);
                                      b.slab_hi = std::max(b.slab_hi, n.dot(x) + pad);
                                    }
                                  });
  // The two-level index: blocks of 8 cells a side, a held block's cells each an entry.
  constexpr int side = 1 << kBlockShift;
  for (int d = 0; d < 3; ++d) blocks_[d] = d < dimension_ ? (cells[d] + side - 1) / side : 1;
  const int block_cells = dimension_ == 1   ? side
                          : dimension_ == 2 ? side * side
                                            : side * side * side;
  block_first_.assign(static_cast<std::size_t>(blocks_.prod()), -1);
  for (const auto& [cell, b] : index) {
    Eigen::Vector3i i;
    long rest = cell;
    for (int d = 2; d >= 0; --d) {
      i[d] = static_cast<int>(rest % cells[d]);
      rest /= cells[d];
    }
    const Eigen::Vector3i block = i.unaryExpr([](int v) { return v >> kBlockShift; });
    int& first = block_first_[static_cast<std::size_t>(
        (static_cast<long>(block[0]) * blocks_[1] + block[1]) * blocks_[2] + block[2])];
    if (first < 0) {
      first = static_cast<int>(cell_bounds_.size());
      cell_bounds_.resize(cell_bounds_.size() + static_cast<std::size_t>(block_cells), -1);
    }
    const Eigen::Vector3i in = i.unaryExpr([](int v) { return v & (side - 1); });
    int place = 0;
    for (int d = 0; d < dimension_; ++d) place = place * side + in[d];
    cell_bounds_[static_cast<std::size_t>(first + place)] = b;
  }
}

int LayerCellFilter::bounds_of(const Eigen::Vector3i& cell) const {
  if (block_first_.empty()) return -1;
  constexpr int side = 1 << kBlockShift;
  long block = 0;
  int place = 0;
  for (int d = 0; d < dimension_; ++d) {
    block = block * blocks_[d] + (cell[d] >> kBlockShift);
    place = place * side + (cell[d] & (side - 1));
  }
  const int first = block_first_[static_cast<std::size_t>(block)];
  return first < 0 ? -1 : cell_bounds_[static_cast<std::size_t>(first + place)];
}

bool LayerCellFilter::may_hold(const Eigen::Vector3i& cell, const Eigen::Vector3d& x) const {
  const int b = bounds_of(cell);
  if (b < 0) return false;
  const Bounds& s = bounds_[static_cast<std::size_t>(b)];
  for (int d = 0; d < dimension_; ++d) {
    const auto u = static_cast<std::size_t>(d);
    if (!(x[d] >= s.lo[u] && x[d] <= s.hi[u])) return false;
  }
  const double along = s.normal[0] * x[0] + s.normal[1] * x[1] + s.normal[2] * x[2];
  return along >= s.slab_lo && along <= s.slab_hi;
}

}  // namespace mpmgeom
