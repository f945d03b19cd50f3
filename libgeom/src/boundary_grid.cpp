// Extrusion of the boundary layer (DESIGN.md section 3, step 3): offset the wall along smoothed
// vertex normals into the material, shrink the offsets where the layer would fold, and lay the
// cells, Gamma and Phi out as the plain arrays of boundary_grid.hpp.
//
// The fold test is exact. A column (one wall facet extruded over the full thickness) is the map
//   x(xi, zeta) = sum_i N_i(xi) (w_i + zeta d_i),   d_i = offset vector of wall vertex i,
// whose Jacobian determinant along the vertical edge above corner i is a polynomial q_i(zeta) of
// degree 2 (3D wedge) or 1 (2D quad), and is linear in the in-plane coordinates for fixed zeta.
// Hence min over the column of det J = min_i min_{zeta in [0,1]} q_i(zeta), computed in closed
// form: a column passing this test has det J > 0 everywhere, not only at its corners. Sub-layer
// cells are zeta-slices of their column, so they pass too.
//
// Scaling all offsets of one column by f maps it onto its own slice zeta in [0, f]. A column that
// first folds (or pinches) at zeta* is therefore repaired by scaling its vertices' offsets by
// f <= zeta*; see fit_offsets() for how shared vertices are reconciled.
//
// Columns that share no cell can still cross (from the two sides of a concave crease, or from
// two walls facing each other) while every cell stays positive. medial_limits() stops each
// vertex's column before it gets closer to another part of the wall than to its own facets.

#include "mpmgeom/boundary_grid.hpp"
#include "format.hpp"

#include <algorithm>
#include <array>
#include <cmath>
#include <functional>
#include <limits>
#include <queue>
#include <sstream>
#include <stdexcept>
#include <string>
#include <unordered_map>
#include <utility>
#include <vector>

#include <Eigen/Geometry>

namespace mpmgeom {

namespace {

/// A column counts as folded where det J <= kFoldLevel * (its nominal det J): positive, with a
/// margin against round-off, but far below any cell one would want to compute with.
constexpr double kFoldLevel = 1e-9;
/// Folding is the extreme of pinching: the volume element det J dropping along a column. Where
/// det J along a vertical edge of a column falls below kPoorPinch times its value at the wall,
/// the column is lowered to the height at which it falls to kTargetPinch times that value. Both
/// only apply where t is comparable to the radius of curvature of a concave wall: on a sphere
/// seen from inside det J at height t is ((R - t) / R)^2 of its value at the wall, so nothing
/// changes up to t = 0.78 R.
constexpr double kPoorPinch = 0.05;
constexpr double kTargetPinch = 0.1;
/// The medial-axis limit of a column (medial_limits): it stops at kMedialMargin of the height
/// where it would be closer to another part of the wall than to its own facets, compared with a
/// relative tolerance so that facets in the planes of its own (a flat or straight wall) do not
/// count as closer by round-off.
constexpr double kMedialMargin = 0.9;
constexpr double kMedialTolerance = 1e-3;
/// Each round lowers at least one offset or clamps it at the minimum; the cap only guards against
/// a slow creep, after which unfolded (merely pinched) columns are accepted.
constexpr int kMaxShrinkRounds = 500;
/// A vertex normal must make an angle below 90 degrees with every facet around the vertex, with
/// this margin on the cosine (otherwise the column is flat at the wall whatever its thickness).
constexpr double kMinNormalCosine = 1e-6;
/// Where a smoothed normal makes more than ~25 degrees with one of its facets (a crease or a
/// corner; on smooth walls at the resolution the grid needs it never does), it is compared with
/// the centre of the facet-normal cone (cone_centre) and replaced by it if its smallest cosine
/// with the facets is below kCreaseRatio times the centre's: smoothing, or a lopsided fan of
/// triangles (a crease point on the boundary of an open mesh), has then tilted it towards one
/// side of the crease, which squeezes the columns on that side.
constexpr double kCreaseCosine = 0.9;
constexpr double kCreaseRatio = 0.9;
/// Largest growth of the offset per unit distance along the wall next to a shrunk column:
/// Phi then rises from a shrunk crease at no more than 45 degrees.
constexpr double kMaxThicknessSlope = 1.0;

using detail::format_number;

template <int Dim>
std::string format_point(const Eigen::Matrix<double, Dim, 1>& p) {
  std::string text = "(";
  for (int i = 0; i < Dim; ++i) text += (i ? ", " : "") + format_number(p[i]);
  return text + ')';
}

[[noreturn]] void fail(const std::string& defect) { throw MeshError("boundary layer: " + defect); }

void check_options(const LayerOptions& options) {
  std::string why;
  if (!options.valid(&why)) throw std::invalid_argument("boundary layer: invalid options: " + why);
}

/// det J along one vertical edge of a column: q(zeta) = c0 + c1 zeta + c2 zeta^2.
struct EdgeJacobian {
  double c0 = 0.0, c1 = 0.0, c2 = 0.0;
  [[nodiscard]] double at(double z) const { return c0 + z * (c1 + z * c2); }

  [[nodiscard]] double min_on_unit_interval() const {
    double m = std::min(at(0.0), at(1.0));
    if (c2 > 0.0) {
      const double z = -c1 / (2.0 * c2);
      if (z > 0.0 && z < 1.0) m = std::min(m, at(z));
    }
    return m;
  }

  /// Smallest zeta in [0, 1] with q(zeta) <= level, or +inf if there is none.
  [[nodiscard]] double first_crossing(double level) const {
    if (at(0.0) <= level) return 0.0;
    double hi = 1.0;
    if (at(1.0) > level) {
      // q(0), q(1) above the level: it can only dip below around an interior minimum.
      if (!(c2 > 0.0)) return std::numeric_limits<double>::infinity();
      const double z = -c1 / (2.0 * c2);
      if (!(z > 0.0 && z < 1.0) || at(z) > level) return std::numeric_limits<double>::infinity();
      hi = z;
    }
    // q(lo) > level >= q(hi), and q - level has exactly one root in (lo, hi].
    double lo = 0.0;
    for (int it = 0; it < 60; ++it) {
      const double mid = 0.5 * (lo + hi);
      (at(mid) > level ? lo : hi) = mid;
    }
    return hi;
  }
};

template <int Dim>
using Point = Eigen::Matrix<double, Dim, 1>;

/// Jacobian determinants along the Dim vertical edges of the column over wall points w with
/// offsets d (Dim = 2: quad over a segment, Dim = 3: wedge over a triangle), and its nominal
/// determinant: that of the straight column of height `thickness` over the same facet.
template <int Dim>
std::array<EdgeJacobian, Dim> column_edges(const std::array<Point<Dim>, Dim>& w,
                                           const std::array<Point<Dim>, Dim>& d) {
  std::array<EdgeJacobian, Dim> q;
  if constexpr (Dim == 2) {
    // dx/ds = e + zeta g, dx/dzeta = d_i at corner i; det = cross(dx/ds, dx/dzeta).
    const Point<2> e = w[1] - w[0], g = d[1] - d[0];
    auto cross = [](const Point<2>& a, const Point<2>& b) { return a.x() * b.y() - a.y() * b.x(); };
    for (int i = 0; i < 2; ++i) q[i] = {cross(e, d[i]), cross(g, d[i]), 0.0};
  } else {
    // dx/dr = e1 + zeta g1, dx/ds = e2 + zeta g2, dx/dzeta = d_i at corner i.
    const Point<3> e1 = w[1] - w[0], e2 = w[2] - w[0], g1 = d[1] - d[0], g2 = d[2] - d[0];
    const Point<3> a0 = e1.cross(e2), a1 = e1.cross(g2) + g1.cross(e2), a2 = g1.cross(g2);
    for (int i = 0; i < 3; ++i) q[i] = {a0.dot(d[i]), a1.dot(d[i]), a2.dot(d[i])};
  }
  return q;
}

/// Length of the segment (2D) or twice the area of the triangle (3D): the in-plane factor of the
/// nominal Jacobian determinant.
template <int Dim>
double facet_jacobian(const std::array<Point<Dim>, Dim>& w) {
  if constexpr (Dim == 2) {
    return (w[1] - w[0]).norm();
  } else {
    return (w[1] - w[0]).cross(w[2] - w[0]).norm();
  }
}

/// The wall as the extrusion sees it: points, one unit normal per point, and the facets
/// (columns) as Dim point indices, ordered so that the facet normal points into the material.
template <int Dim>
struct Wall {
  std::vector<Point<Dim>> points;
  std::vector<Point<Dim>> normals;  ///< per point, unit
  std::vector<std::array<int, Dim>> facets;
  std::vector<Point<Dim>> facet_normals;       ///< per facet, unit
  std::vector<std::vector<int>> neighbours;    ///< per point, the points sharing an edge with it
  std::vector<std::vector<int>> point_facets;  ///< per point, the facets around it
  std::function<std::string(std::size_t)> describe;  ///< "triangle 3 near (x, y, z)"
};

template <int Dim>
std::array<Point<Dim>, Dim> facet_points(const Wall<Dim>& wall, std::size_t f) {
  std::array<Point<Dim>, Dim> w;
  for (int i = 0; i < Dim; ++i) w[i] = wall.points[wall.facets[f][i]];
  return w;
}

template <int Dim>
std::array<Point<Dim>, Dim> facet_offsets(const Wall<Dim>& wall, std::size_t f,
                                          const std::vector<double>& offset) {
  std::array<Point<Dim>, Dim> d;
  for (int i = 0; i < Dim; ++i) {
    const int v = wall.facets[f][i];
    d[i] = offset[v] * wall.normals[v];
  }
  return d;
}

/// Smallest cosine between n and the normals of the facets around point v.
template <int Dim>
double worst_cosine(const Wall<Dim>& wall, int v, const Point<Dim>& n) {
  double worst = 1.0;
  for (const int f : wall.point_facets[v]) worst = std::min(worst, n.dot(wall.facet_normals[f]));
  return worst;
}

/// The unit vector that maximises the smallest cosine with the facet normals around v: the
/// centre of the smallest spherical cap holding them. It is fixed by one, two or three of them
/// (the cap's centre is that normal, the bisector of two, or the circumcentre of three), so the
/// candidates are enumerated; a point has a handful of facets.
template <int Dim>
Point<Dim> cone_centre(const Wall<Dim>& wall, int v) {
  std::vector<Point<Dim>> n;
  for (const int f : wall.point_facets[v]) n.push_back(wall.facet_normals[f]);
  Point<Dim> best = wall.normals[v];
  double best_cosine = worst_cosine(wall, v, best);
  auto consider = [&](Point<Dim> candidate) {
    const double length = candidate.norm();
    if (!(length > 1e-12)) return;
    candidate /= length;
    const double cosine = worst_cosine(wall, v, candidate);
    if (cosine > best_cosine) best = candidate, best_cosine = cosine;
  };
  const std::size_t m = n.size();
  for (std::size_t i = 0; i < m; ++i) {
    consider(n[i]);
    for (std::size_t j = i + 1; j < m; ++j) {
      consider(n[i] + n[j]);
      if constexpr (Dim == 3) {
        for (std::size_t k = j + 1; k < m; ++k) {
          Point<3> centre = (n[j] - n[i]).cross(n[k] - n[i]);
          if (centre.dot(n[i]) < 0.0) centre = -centre;
          consider(centre);
        }
      }
    }
  }
  return best;
}

/// Laplacian smoothing of unit normals over the neighbours of each point (Jacobi passes,
/// n <- normalise(n + mean of neighbours)). At creases and corners a normal tilted towards one
/// side (see kCreaseCosine) is replaced by the centre of its facet-normal cone, the direction
/// that stays furthest inside every facet's material side. If a normal is not inside all of
/// them after that, the wall folds back on itself there: MeshError. Returns the number of
/// replaced normals.
template <int Dim>
std::size_t smooth_normals(Wall<Dim>& wall, int passes) {
  for (int pass = 0; pass < passes; ++pass) {
    std::vector<Point<Dim>> next = wall.normals;
    for (std::size_t v = 0; v < next.size(); ++v) {
      if (wall.neighbours[v].empty()) continue;
      Point<Dim> mean = Point<Dim>::Zero();
      for (const int u : wall.neighbours[v]) mean += wall.normals[u];
      const Point<Dim> sum =
          wall.normals[v] + mean / static_cast<double>(wall.neighbours[v].size());
      if (sum.norm() > 1e-12) next[v] = sum.normalized();
    }
    wall.normals.swap(next);
  }
  std::size_t replaced = 0;
  for (std::size_t v = 0; v < wall.points.size(); ++v) {
    const int point = static_cast<int>(v);
    const double worst = worst_cosine(wall, point, wall.normals[v]);
    if (worst >= kCreaseCosine) continue;
    const Point<Dim> centre = cone_centre(wall, point);
    if (worst < kCreaseRatio * worst_cosine(wall, point, centre)) {
      wall.normals[v] = centre;
      ++replaced;
    }
    for (const int f : wall.point_facets[v]) {
      const double cosine = wall.normals[v].dot(wall.facet_normals[f]);
      if (cosine <= kMinNormalCosine) {
        fail("cannot extrude the layer at " + wall.describe(f) + ": at its vertex " +
             std::to_string(v) + " " + format_point<Dim>(wall.points[v]) +
             " no direction points into the material side of every facet around it (best "
             "cosine " +
             format_number(cosine) +
             "); the wall has an edge folded back on itself or an inconsistent orientation");
      }
    }
  }
  return replaced;
}

/// Distance from p to a wall facet: a segment (2D) or a triangle (3D; closest point by the
/// Voronoi regions of the vertices, edges and face, Ericson, Real-Time Collision Detection 5.1.5).
double facet_distance(const Point<2>& p, const std::array<Point<2>, 2>& w) {
  const Point<2> e = w[1] - w[0];
  const double u = std::clamp((p - w[0]).dot(e) / e.squaredNorm(), 0.0, 1.0);
  return (p - (w[0] + u * e)).norm();
}

double facet_distance(const Point<3>& p, const std::array<Point<3>, 3>& w) {
  const Point<3>&a = w[0], &b = w[1], &c = w[2];
  const Point<3> ab = b - a, ac = c - a, ap = p - a;
  const double d1 = ab.dot(ap), d2 = ac.dot(ap);
  if (d1 <= 0.0 && d2 <= 0.0) return ap.norm();
  const Point<3> bp = p - b;
  const double d3 = ab.dot(bp), d4 = ac.dot(bp);
  if (d3 >= 0.0 && d4 <= d3) return bp.norm();
  const double vc = d1 * d4 - d3 * d2;
  if (vc <= 0.0 && d1 >= 0.0 && d3 <= 0.0) return (p - (a + d1 / (d1 - d3) * ab)).norm();
  const Point<3> cp = p - c;
  const double d5 = ab.dot(cp), d6 = ac.dot(cp);
  if (d6 >= 0.0 && d5 <= d6) return cp.norm();
  const double vb = d5 * d2 - d1 * d6;
  if (vb <= 0.0 && d2 >= 0.0 && d6 <= 0.0) return (p - (a + d2 / (d2 - d6) * ac)).norm();
  const double va = d3 * d6 - d5 * d4;
  if (va <= 0.0 && d4 - d3 >= 0.0 && d5 - d6 >= 0.0) {
    return (p - (b + (d4 - d3) / ((d4 - d3) + (d5 - d6)) * (c - b))).norm();
  }
  const double denom = 1.0 / (va + vb + vc);
  return (p - (a + ab * (vb * denom) + ac * (vc * denom))).norm();
}

/// Facets bucketed in a uniform grid of cubes (squares) of side `cell`, for the facets near a
/// point. Facets spanning more than kMaxSpan cells per axis are kept aside and always returned.
template <int Dim>
class FacetBuckets {
 public:
  FacetBuckets(const Wall<Dim>& wall, double cell) : cell_(cell) {
    for (std::size_t f = 0; f < wall.facets.size(); ++f) {
      Point<Dim> lo = wall.points[wall.facets[f][0]], hi = lo;
      for (const int v : wall.facets[f]) {
        lo = lo.cwiseMin(wall.points[v]);
        hi = hi.cwiseMax(wall.points[v]);
      }
      const auto first = key(lo), last = key(hi);
      bool huge = false;
      for (int i = 0; i < Dim; ++i) huge = huge || last[i] - first[i] > kMaxSpan;
      if (huge) {
        large_.push_back(static_cast<int>(f));
        continue;
      }
      for_cells(first, last, [&](const Key& k) { buckets_[k].push_back(static_cast<int>(f)); });
    }
  }

  /// Calls visit(f) for every facet that may meet the box [lo, hi] (possibly more than once).
  template <class Visit>
  void near(const Point<Dim>& lo, const Point<Dim>& hi, Visit&& visit) const {
    for (const int f : large_) visit(f);
    for_cells(key(lo), key(hi), [&](const Key& k) {
      const auto it = buckets_.find(k);
      if (it != buckets_.end()) {
        for (const int f : it->second) visit(f);
      }
    });
  }

 private:
  static constexpr long kMaxSpan = 32;
  using Key = std::array<long, Dim>;
  struct Hash {
    std::size_t operator()(const Key& k) const {
      std::size_t h = 0;
      for (const long c : k) h = h * 0x9E3779B97F4A7C15ull + static_cast<std::size_t>(c);
      return h;
    }
  };
  Key key(const Point<Dim>& x) const {
    Key k;
    for (int i = 0; i < Dim; ++i) k[i] = static_cast<long>(std::floor(x[i] / cell_));
    return k;
  }
  template <class Visit>
  static void for_cells(const Key& first, const Key& last, Visit&& visit) {
    Key k = first;
    while (true) {
      visit(k);
      int i = 0;
      while (i < Dim && k[i] == last[i]) k[i] = first[i], ++i;
      if (i == Dim) return;
      ++k[i];
    }
  }
  double cell_;
  std::unordered_map<Key, std::vector<int>, Hash> buckets_;
  std::vector<int> large_;
};

/// How far each point's column may rise before it crosses the medial axis of the wall: the
/// first height s at which x_v + s n_v is closer to a facet outside the star of v (the facets
/// around v) than to the planes of its own facets (s times the smallest cosine between n_v and
/// them), times kMedialMargin; `thickness` if that does not happen below it. Past that height
/// the column would run into the layer of another part of the wall: across a concave crease or
/// corner (where columns that share no cell cross without any cell folding) or from a wall
/// facing another one closer than 2 t. The first crossing is found by sphere tracing along the
/// column, then bisection.
template <int Dim>
std::vector<double> medial_limits(const Wall<Dim>& wall, double thickness,
                                  std::vector<int>* blocking_facet) {
  double mean_edge = 0.0;
  std::size_t edges = 0;
  for (std::size_t v = 0; v < wall.points.size(); ++v) {
    for (const int u : wall.neighbours[v]) mean_edge += (wall.points[u] - wall.points[v]).norm();
    edges += wall.neighbours[v].size();
  }
  mean_edge = edges ? mean_edge / static_cast<double>(edges) : thickness;
  const FacetBuckets<Dim> buckets(wall, std::max(thickness, mean_edge));

  std::vector<double> limit(wall.points.size(), thickness);
  blocking_facet->assign(wall.points.size(), -1);
  std::vector<std::size_t> seen(wall.facets.size(), 0);  // stamp v + 1 when visited for v
  for (std::size_t v = 0; v < wall.points.size(); ++v) {
    const Point<Dim>& x = wall.points[v];
    const Point<Dim>& n = wall.normals[v];
    const double own = (1.0 - kMedialTolerance) * worst_cosine(wall, static_cast<int>(v), n);
    for (const int f : wall.point_facets[v]) seen[f] = v + 1;
    const Point<Dim> top = x + thickness * n;
    const Point<Dim> reach = Point<Dim>::Constant(thickness);
    buckets.near(x.cwiseMin(top) - reach, x.cwiseMax(top) + reach, [&](int f) {
      if (seen[f] == v + 1) return;
      seen[f] = v + 1;
      const auto w = facet_points(wall, static_cast<std::size_t>(f));
      const double height = limit[v] / kMedialMargin;
      auto gap = [&](double s) { return facet_distance(Point<Dim>(x + s * n), w) - own * s; };
      // A facet through the point itself (an unwelded seam or a non-manifold vertex) says
      // nothing about the medial axis; the cell checks look after the neighbourhood.
      if (!(gap(0.0) > 1e-12 * thickness)) return;
      // Cheap rejection: the distance to the facet is at least that to its plane (3D) or line.
      if constexpr (Dim == 3) {
        const Point<3>& normal = wall.facet_normals[static_cast<std::size_t>(f)];
        const double a = (x - w[0]).dot(normal), b = n.dot(normal);
        auto plane_gap = [&](double s) { return std::abs(a + b * s) - own * s; };
        double lowest = std::min(plane_gap(0.0), plane_gap(height));
        if (b != 0.0 && -a / b > 0.0 && -a / b < height) {
          lowest = std::min(lowest, plane_gap(-a / b));
        }
        if (lowest >= 0.0) return;  // the gap is at least the plane gap
      }
      // Sphere tracing: the gap changes by at most (1 + own) per unit of s, so stepping by
      // gap / (1 + own) cannot jump over its first zero.
      const double lipschitz = 1.0 + std::abs(own);
      double lo = 0.0, g = gap(0.0);
      while (g > 0.0) {
        const double next = lo + std::max(g / lipschitz, 1e-6 * height);
        if (next >= height) return;
        const double g_next = gap(next);
        if (g_next <= 0.0) break;
        lo = next, g = g_next;
      }
      double hi = std::min(height, lo + std::max(g / lipschitz, 1e-6 * height));
      for (int it = 0; it < 20; ++it) {
        const double mid = 0.5 * (lo + hi);
        (gap(mid) > 0.0 ? lo : hi) = mid;
      }
      if (kMedialMargin * hi < limit[v]) {
        limit[v] = kMedialMargin * hi;
        (*blocking_facet)[v] = f;
      }
    });
  }
  return limit;
}

struct Fit {
  std::vector<double> scale;  ///< per wall point, offset = scale * thickness
  double min_jacobian = std::numeric_limits<double>::infinity();
};

/// Caps the thickness so that it grows by at most kMaxThicknessSlope per unit of distance
/// along wall edges: t_u <= t_v + slope |x_u - x_v| (a Dijkstra sweep; it only lowers scales).
/// Without it a shrunk crease leaves a deep, steep-walled notch in Phi.
template <int Dim>
void grade_thickness(const Wall<Dim>& wall, double thickness, std::vector<double>& scale) {
  using Entry = std::pair<double, int>;
  std::priority_queue<Entry, std::vector<Entry>, std::greater<>> queue;
  for (std::size_t v = 0; v < scale.size(); ++v) {
    if (scale[v] < 1.0) queue.emplace(scale[v], static_cast<int>(v));
  }
  while (!queue.empty()) {
    const auto [s, v] = queue.top();
    queue.pop();
    if (s > scale[v]) continue;  // stale entry
    for (const int u : wall.neighbours[v]) {
      const double reach =
          s + kMaxThicknessSlope * (wall.points[u] - wall.points[v]).norm() / thickness;
      if (reach < scale[u]) {
        scale[u] = reach;
        queue.emplace(reach, u);
      }
    }
  }
}

/// Offsets that keep det J > 0 in every column, and above kPoorPinch of its wall value where the
/// allowed shrinking permits. Start from the full thickness capped by the medial limits (an
/// error if one is below min_thickness_fraction) and graded; in each round, every pinched or
/// folded column asks for its vertices' offsets to be scaled by the height zeta* at which its
/// det J falls to kTargetPinch of the wall value (scaling a column's offsets by zeta* maps it onto
/// its own slice [0, zeta*]); a vertex shared by several columns takes the smallest request,
/// never going below min_thickness_fraction; then the thickness is graded around the shrunk
/// vertices. Shared vertices make the scaling of a column non-uniform, and shrinking one column
/// can tilt a neighbour, so columns are rechecked until none asks for more. When nothing can
/// change any more, a column that still folds is a MeshError naming the worst one; columns that
/// are merely pinched are accepted.
template <int Dim>
Fit fit_offsets(const Wall<Dim>& wall, const LayerOptions& options) {
  const std::size_t n_facets = wall.facets.size();
  const double t = options.thickness;
  std::vector<double> nominal(n_facets);
  for (std::size_t f = 0; f < n_facets; ++f) {
    nominal[f] = facet_jacobian<Dim>(facet_points(wall, f)) * t;
  }

  Fit fit;
  std::vector<int> blocking;
  const std::vector<double> limit = medial_limits(wall, t, &blocking);
  fit.scale.resize(wall.points.size());
  for (std::size_t v = 0; v < limit.size(); ++v) {
    fit.scale[v] = limit[v] / t;
    if (fit.scale[v] < options.min_thickness_fraction) {
      const auto w = facet_points(wall, static_cast<std::size_t>(blocking[v]));
      Point<Dim> centre = Point<Dim>::Zero();
      for (const auto& x : w) centre += x / Dim;
      fail("cannot extrude the layer at " + wall.describe(wall.point_facets[v].front()) +
           ": the column of its vertex " + std::to_string(v) + " " +
           format_point<Dim>(wall.points[v]) + " meets the layer of the wall near " +
           format_point<Dim>(centre) + " at " + format_number(fit.scale[v]) + " of the thickness " +
           format_number(t) +
           ", below min_thickness_fraction (a crease too sharp for this thickness, or walls "
           "closer than twice the thickness)");
    }
  }
  grade_thickness(wall, t, fit.scale);
  std::vector<double> offset(wall.points.size());
  for (int round = 0;; ++round) {
    for (std::size_t v = 0; v < offset.size(); ++v) offset[v] = fit.scale[v] * t;
    std::vector<double> next = fit.scale;
    bool folded = false, pinched = false;
    std::size_t worst = 0;
    double worst_ratio = std::numeric_limits<double>::infinity();
    fit.min_jacobian = std::numeric_limits<double>::infinity();
    for (std::size_t f = 0; f < n_facets; ++f) {
      const auto q = column_edges<Dim>(facet_points(wall, f), facet_offsets(wall, f, offset));
      double min_det = std::numeric_limits<double>::infinity(), pinch = 1.0;
      for (const auto& edge : q) {
        const double lowest = edge.min_on_unit_interval();
        min_det = std::min(min_det, lowest);
        pinch = std::min(pinch, edge.c0 > 0.0 ? lowest / edge.c0 : -1.0);
      }
      const double ratio = min_det / nominal[f];
      fit.min_jacobian = std::min(fit.min_jacobian, ratio);
      if (pinch >= kPoorPinch && ratio > kFoldLevel) continue;
      pinched = true;
      if (ratio <= kFoldLevel) {
        folded = true;
        if (ratio < worst_ratio) worst_ratio = ratio, worst = f;
      }
      double height = 1.0;
      for (const auto& edge : q) {
        height = std::min(height, edge.first_crossing(kTargetPinch * edge.c0));
      }
      for (const int v : wall.facets[f]) {
        const double wanted = std::max(options.min_thickness_fraction, fit.scale[v] * height);
        if (wanted < next[v]) next[v] = wanted;
      }
    }
    if (!pinched) return fit;
    grade_thickness(wall, t, next);
    bool changed = false;
    for (std::size_t v = 0; v < next.size(); ++v) {
      if (next[v] < fit.scale[v] * (1.0 - 1e-12)) changed = true;
    }
    if (changed && round < kMaxShrinkRounds) {
      fit.scale.swap(next);
      continue;
    }
    if (!folded) return fit;
    double smallest = 1.0;
    for (const int v : wall.facets[worst]) smallest = std::min(smallest, fit.scale[v]);
    fail("cannot extrude the layer at " + wall.describe(worst) +
         ": the layer folds there (smallest Jacobian " + format_number(worst_ratio) +
         " of nominal) with its offsets shrunk to " + format_number(smallest) +
         " of the thickness " + format_number(t) +
         "; reduce the thickness, lower min_thickness_fraction or smooth the wall");
  }
}

/// Nodes, cells, facets and flags shared by the 2D and 3D layouts: node k * P + v lies on level
/// k (0 = wall, K = interface) above wall point v; cell k * F + f is sub-layer k of column f.
template <int Dim>
BoundaryGrid lay_out(const Wall<Dim>& wall, const Fit& fit, const LayerOptions& options) {
  const int K = options.layers;
  const auto P = static_cast<Eigen::Index>(wall.points.size());
  const auto F = static_cast<Eigen::Index>(wall.facets.size());
  BoundaryGrid grid;
  grid.dimension = Dim;
  grid.layers = K;
  grid.thickness = options.thickness;
  grid.nodes.resize((K + 1) * P, Dim);
  grid.node_normals.resize((K + 1) * P, Dim);
  grid.node_on_wall = Eigen::VectorXi::Zero((K + 1) * P);
  grid.node_on_interface = Eigen::VectorXi::Zero((K + 1) * P);
  for (int k = 0; k <= K; ++k) {
    for (Eigen::Index v = 0; v < P; ++v) {
      const double height = fit.scale[v] * options.thickness * k / K;
      grid.nodes.row(k * P + v) = (wall.points[v] + height * wall.normals[v]).transpose();
      grid.node_normals.row(k * P + v) = wall.normals[v].transpose();
    }
  }
  grid.node_on_wall.head(P).setOnes();
  grid.node_on_interface.tail(P).setOnes();

  grid.cells.resize(K * F, 2 * Dim);
  grid.cell_layer.resize(K * F);
  for (int k = 0; k < K; ++k) {
    for (Eigen::Index f = 0; f < F; ++f) {
      for (int i = 0; i < Dim; ++i) {
        grid.cells(k * F + f, i) = static_cast<int>(k * P) + wall.facets[f][i];
        grid.cells(k * F + f, Dim + i) = static_cast<int>((k + 1) * P) + wall.facets[f][i];
      }
      grid.cell_layer(k * F + f) = k;
    }
  }
  grid.wall_facets.resize(F, Dim);
  grid.interface_facets.resize(F, Dim);
  for (Eigen::Index f = 0; f < F; ++f) {
    for (int i = 0; i < Dim; ++i) {
      grid.wall_facets(f, i) = wall.facets[f][i];
      grid.interface_facets(f, i) = static_cast<int>(K * P) + wall.facets[f][i];
    }
  }
  return grid;
}

/// Layer volume (3D) or area (2D), exact. Each cell is a column in its own right (bottom nodes
/// w_i, offsets d_i = top - bottom), det J is linear in the in-plane coordinates, so its integral
/// over the reference triangle (area 1/2) or segment (length 1) is the mean over the corners,
/// and along the vertical edge above corner i the integral of q_i over [0, 1] is
/// c0 + c1 / 2 + c2 / 3.
template <int Dim>
double layer_measure(const BoundaryGrid& grid) {
  double total = 0.0;
  for (Eigen::Index c = 0; c < grid.cells.rows(); ++c) {
    std::array<Point<Dim>, Dim> w, d;
    for (int i = 0; i < Dim; ++i) {
      w[i] = grid.nodes.row(grid.cells(c, i)).transpose();
      d[i] = grid.nodes.row(grid.cells(c, Dim + i)).transpose() - w[i];
    }
    double sum = 0.0;
    for (const auto& q : column_edges<Dim>(w, d)) sum += q.c0 + q.c1 / 2.0 + q.c2 / 3.0;
    total += sum / (Dim == 2 ? 2.0 : 6.0);
  }
  return total;
}

/// Total area (3D) or length (2D) of a facet list.
double facet_measure(const BoundaryGrid& grid, const Eigen::MatrixXi& facets) {
  double total = 0.0;
  for (Eigen::Index f = 0; f < facets.rows(); ++f) {
    if (grid.dimension == 2) {
      total += (grid.nodes.row(facets(f, 1)) - grid.nodes.row(facets(f, 0))).norm();
    } else {
      const Eigen::Vector3d a = grid.nodes.row(facets(f, 0)), b = grid.nodes.row(facets(f, 1)),
                            c = grid.nodes.row(facets(f, 2));
      total += 0.5 * (b - a).cross(c - a).norm();
    }
  }
  return total;
}

void fill_report(const BoundaryGrid& grid, const Fit& fit, std::size_t crease_normals,
                 LayerReport* report) {
  if (!report) return;
  *report = LayerReport{};
  report->cells = grid.cell_count();
  report->nodes = static_cast<std::size_t>(grid.nodes.rows());
  for (const double s : fit.scale) {
    if (s < 1.0) ++report->columns_shrunk;
    report->max_shrink = std::max(report->max_shrink, 1.0 - s);
  }
  report->crease_normals = crease_normals;
  report->min_jacobian = fit.min_jacobian;
  report->volume = grid.dimension == 2 ? layer_measure<2>(grid) : layer_measure<3>(grid);
  report->wall_measure = facet_measure(grid, grid.wall_facets);
  report->interface_measure = facet_measure(grid, grid.interface_facets);
}

}  // namespace

bool LayerOptions::valid(std::string* why) const {
  auto no = [why](const std::string& reason) {
    if (why) *why = reason;
    return false;
  };
  if (!std::isfinite(thickness) || !(thickness > 0.0)) {
    return no("thickness must be finite and positive (got " + format_number(thickness) + ")");
  }
  if (layers < 1) return no("layers must be at least 1 (got " + std::to_string(layers) + ")");
  if (normal_smoothing < 0) {
    return no("normal_smoothing must be >= 0 (got " + std::to_string(normal_smoothing) + ")");
  }
  if (!std::isfinite(min_thickness_fraction) || !(min_thickness_fraction > 0.0) ||
      min_thickness_fraction > 1.0) {
    return no("min_thickness_fraction must be in (0, 1] (got " +
              format_number(min_thickness_fraction) + ")");
  }
  return true;
}

BoundaryGrid extrude_layer(const TriangleMesh& wall, const LayerOptions& options,
                           LayerReport* report) {
  check_options(options);
  const Eigen::Index n_faces = wall.F.rows();
  if (n_faces == 0 || wall.V.rows() == 0) fail("the wall mesh has no triangles");
  if (wall.part.size() != 0 && wall.part.size() != n_faces) {
    fail("the wall mesh has " + std::to_string(wall.part.size()) + " part indices for " +
         std::to_string(n_faces) + " triangles");
  }
  const auto n_parts = static_cast<int>(wall.part_names.size());
  for (Eigen::Index f = 0; f < wall.part.size(); ++f) {
    if (wall.part(f) < 0 || wall.part(f) >= std::max(n_parts, 1)) {
      fail("triangle " + std::to_string(f) + " has part index " + std::to_string(wall.part(f)) +
           " but the wall mesh names " + std::to_string(n_parts) + " parts");
    }
  }

  // Wall points: the referenced vertices of V in their original order (so they are V itself for
  // a mesh from load_mesh()).
  std::vector<int> point_of(static_cast<std::size_t>(wall.V.rows()), -1);
  for (Eigen::Index f = 0; f < n_faces; ++f) {
    for (int i = 0; i < 3; ++i) {
      const int v = wall.F(f, i);
      if (v < 0 || v >= wall.V.rows()) {
        fail("triangle " + std::to_string(f) + " refers to vertex " + std::to_string(v) + " of " +
             std::to_string(wall.V.rows()));
      }
      point_of[v] = 0;
    }
  }
  Wall<3> layer_wall;
  for (std::size_t v = 0; v < point_of.size(); ++v) {
    if (point_of[v] < 0) continue;
    const Point<3> x = wall.V.row(static_cast<Eigen::Index>(v)).transpose();
    if (!x.allFinite()) fail("vertex " + std::to_string(v) + " has a non-finite coordinate");
    point_of[v] = static_cast<int>(layer_wall.points.size());
    layer_wall.points.push_back(x);
  }
  layer_wall.facets.resize(static_cast<std::size_t>(n_faces));
  for (Eigen::Index f = 0; f < n_faces; ++f) {
    for (int i = 0; i < 3; ++i) layer_wall.facets[f][i] = point_of[wall.F(f, i)];
  }
  layer_wall.describe = [&layer_wall](std::size_t f) {
    const auto& [a, b, c] = layer_wall.facets[f];
    const Point<3> centroid =
        (layer_wall.points[a] + layer_wall.points[b] + layer_wall.points[c]) / 3.0;
    return "triangle " + std::to_string(f) + " near " + format_point<3>(centroid);
  };

  // Angle-weighted vertex normals (Thuermer & Wuethrich): unlike area weights they do not depend
  // on how a flat region happens to be triangulated.
  const std::size_t n_points = layer_wall.points.size();
  auto& facet_normals = layer_wall.facet_normals;
  auto& neighbours = layer_wall.neighbours;
  facet_normals.resize(static_cast<std::size_t>(n_faces));
  layer_wall.normals.assign(n_points, Point<3>::Zero());
  neighbours.resize(n_points);
  layer_wall.point_facets.resize(n_points);
  for (std::size_t f = 0; f < facet_normals.size(); ++f) {
    const auto w = facet_points(layer_wall, f);
    const Point<3> n = (w[1] - w[0]).cross(w[2] - w[0]);
    const double longest =
        std::max({(w[1] - w[0]).norm(), (w[2] - w[1]).norm(), (w[0] - w[2]).norm()});
    if (!(n.norm() > 1e-12 * longest * longest)) {
      fail("triangle " + std::to_string(f) + " near " + format_point<3>(w[0]) +
           " is degenerate (zero area); repair the wall mesh first");
    }
    facet_normals[f] = n.normalized();
    for (int i = 0; i < 3; ++i) {
      const Point<3> e1 = w[(i + 1) % 3] - w[i], e2 = w[(i + 2) % 3] - w[i];
      const double angle = std::atan2(e1.cross(e2).norm(), e1.dot(e2));
      const int v = layer_wall.facets[f][i];
      layer_wall.normals[v] += angle * facet_normals[f];
      layer_wall.point_facets[v].push_back(static_cast<int>(f));
      neighbours[v].push_back(layer_wall.facets[f][(i + 1) % 3]);
      neighbours[v].push_back(layer_wall.facets[f][(i + 2) % 3]);
    }
  }
  for (std::size_t v = 0; v < n_points; ++v) {
    std::sort(neighbours[v].begin(), neighbours[v].end());
    neighbours[v].erase(std::unique(neighbours[v].begin(), neighbours[v].end()),
                        neighbours[v].end());
    // The angles around a vertex sum to at least a few degrees, so a tiny sum means the facet
    // normals cancel (facets folded back onto each other).
    const double length = layer_wall.normals[v].norm();
    if (!(length > 1e-9)) {
      fail("cannot extrude the layer at vertex " + std::to_string(v) + " " +
           format_point<3>(layer_wall.points[v]) +
           ": its triangles face opposite ways, so it has no normal; check the orientation");
    }
    layer_wall.normals[v] /= length;
  }
  const std::size_t replaced = smooth_normals(layer_wall, options.normal_smoothing);

  const Fit fit = fit_offsets<3>(layer_wall, options);
  BoundaryGrid grid = lay_out<3>(layer_wall, fit, options);

  grid.part_names = wall.part_names.empty() ? std::vector<std::string>{"wall"} : wall.part_names;
  grid.wall_facet_part = wall.part.size() == n_faces
                             ? Eigen::VectorXi(wall.part)
                             : Eigen::VectorXi(Eigen::VectorXi::Zero(n_faces));
  grid.cell_part = grid.wall_facet_part.replicate(options.layers, 1);
  fill_report(grid, fit, replaced, report);
  return grid;
}

BoundaryGrid extrude_layer_2d(const Eigen::MatrixX2d& polyline, bool closed,
                              const LayerOptions& options, const std::string& part_name,
                              LayerReport* report) {
  check_options(options);
  const auto n_points = static_cast<std::size_t>(polyline.rows());
  if (n_points < 2) {
    fail("the wall polyline needs at least 2 points (got " + std::to_string(n_points) + ")");
  }
  if (closed && n_points < 3) fail("a closed wall polyline needs at least 3 points");

  Wall<2> layer_wall;
  for (std::size_t v = 0; v < n_points; ++v) {
    const Point<2> x = polyline.row(static_cast<Eigen::Index>(v)).transpose();
    if (!x.allFinite()) fail("polyline point " + std::to_string(v) + " is not finite");
    layer_wall.points.push_back(x);
  }
  const std::size_t n_segments = closed ? n_points : n_points - 1;
  for (std::size_t s = 0; s < n_segments; ++s) {
    layer_wall.facets.push_back({static_cast<int>(s), static_cast<int>((s + 1) % n_points)});
  }
  layer_wall.describe = [&layer_wall](std::size_t s) {
    const auto& [a, b] = layer_wall.facets[s];
    return "segment " + std::to_string(s) + " near " +
           format_point<2>(0.5 * (layer_wall.points[a] + layer_wall.points[b]));
  };

  // Left normals of the segments; a point's normal is the normalised sum of the unit normals of
  // its (one or two) segments, i.e. the bisector of the corner.
  auto& facet_normals = layer_wall.facet_normals;
  auto& neighbours = layer_wall.neighbours;
  facet_normals.resize(n_segments);
  layer_wall.normals.assign(n_points, Point<2>::Zero());
  neighbours.resize(n_points);
  layer_wall.point_facets.resize(n_points);
  for (std::size_t s = 0; s < n_segments; ++s) {
    const auto [a, b] = layer_wall.facets[s];
    const Point<2> along = layer_wall.points[b] - layer_wall.points[a];
    const double scale = std::max(layer_wall.points[a].norm(), layer_wall.points[b].norm());
    if (!(along.norm() > 1e-14 * scale)) {
      fail("segment " + std::to_string(s) + " of the wall polyline has zero length at " +
           format_point<2>(layer_wall.points[a]) +
           " (repeated point; a closed polyline must not repeat its first point at the end)");
    }
    facet_normals[s] = Point<2>(-along.y(), along.x()).normalized();
    layer_wall.normals[a] += facet_normals[s];
    layer_wall.normals[b] += facet_normals[s];
    neighbours[a].push_back(b);
    neighbours[b].push_back(a);
    layer_wall.point_facets[a].push_back(static_cast<int>(s));
    layer_wall.point_facets[b].push_back(static_cast<int>(s));
  }
  for (std::size_t v = 0; v < n_points; ++v) {
    const double length = layer_wall.normals[v].norm();
    if (!(length > 1e-9)) {
      fail("cannot extrude the layer at polyline point " + std::to_string(v) + " " +
           format_point<2>(layer_wall.points[v]) + ": the polyline turns back on itself there");
    }
    layer_wall.normals[v] /= length;
  }
  const std::size_t replaced = smooth_normals(layer_wall, options.normal_smoothing);

  const Fit fit = fit_offsets<2>(layer_wall, options);
  BoundaryGrid grid = lay_out<2>(layer_wall, fit, options);
  grid.part_names = {part_name};
  grid.cell_part = Eigen::VectorXi::Zero(grid.cells.rows());
  grid.wall_facet_part = Eigen::VectorXi::Zero(grid.wall_facets.rows());
  fill_report(grid, fit, replaced, report);
  return grid;
}

BoundaryGrid layer_1d(double wall_point, int side, const LayerOptions& options,
                      const std::string& part_name, LayerReport* report) {
  check_options(options);
  if (side != 1 && side != -1) {
    throw std::invalid_argument("boundary layer: side must be +1 or -1 (got " +
                                std::to_string(side) + ")");
  }
  if (!std::isfinite(wall_point)) fail("the wall point is not finite");
  const int K = options.layers;
  BoundaryGrid grid;
  grid.dimension = 1;
  grid.layers = K;
  grid.thickness = options.thickness;
  grid.nodes.resize(K + 1, 1);
  for (int k = 0; k <= K; ++k) grid.nodes(k, 0) = wall_point + side * options.thickness * k / K;
  grid.cells.resize(K, 2);
  grid.cell_layer.resize(K);
  for (int k = 0; k < K; ++k) {
    grid.cells(k, 0) = k;
    grid.cells(k, 1) = k + 1;
    grid.cell_layer(k) = k;
  }
  grid.cell_part = Eigen::VectorXi::Zero(K);
  grid.part_names = {part_name};
  grid.wall_facets = Eigen::MatrixXi::Constant(1, 1, 0);
  grid.interface_facets = Eigen::MatrixXi::Constant(1, 1, K);
  grid.wall_facet_part = Eigen::VectorXi::Zero(1);
  grid.node_normals = Eigen::MatrixXd::Constant(K + 1, 1, side);
  grid.node_on_wall = Eigen::VectorXi::Zero(K + 1);
  grid.node_on_interface = Eigen::VectorXi::Zero(K + 1);
  grid.node_on_wall(0) = 1;
  grid.node_on_interface(K) = 1;
  if (report) {
    *report = LayerReport{};
    report->cells = static_cast<std::size_t>(K);
    report->nodes = static_cast<std::size_t>(K + 1);
    report->min_jacobian = 1.0;  // side * dx/dzeta = t / K in every cell, its nominal value
    report->volume = options.thickness;
    report->wall_measure = 1.0;
    report->interface_measure = 1.0;
  }
  return grid;
}

}  // namespace mpmgeom
