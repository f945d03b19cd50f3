// Point queries with Embree (DESIGN.md section 3, point 5).
//
// Embree works in float; every answer here is decided in double:
//  - LayerLocator: Embree only proposes candidate cells (user geometry whose boxes are the cell
//    bounds rounded outward to float and padded); Newton on the isoparametric map in double says
//    which candidate holds the point and where.
//  - ClosedSurface: Embree collects every triangle a ray may cross (an intersection filter that
//    records and rejects each hit); the crossings are then recounted in double with Pluecker-style
//    edge tests that agree exactly between the two triangles of a shared edge. A ray passing
//    within a margin of an edge or vertex, or grazing a face, is discarded and cast again in the
//    next fixed direction; if every direction is ambiguous the generalized winding number
//    decides. Closest points come from a point query whose callback computes exact
//    point-triangle distances in double.
// Both objects shift their Embree frame to the centre of their bounding box, so float round-off
// scales with the size of the geometry, not with its distance from the origin.

#include "mpmgeom/locator.hpp"

#include <embree3/rtcore.h>

#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>

#include <Eigen/Dense>

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdint>
#include <limits>
#include <mutex>
#include <numbers>
#include <stdexcept>
#include <string>

namespace mpmgeom {
namespace {

constexpr double kInf = std::numeric_limits<double>::infinity();
constexpr double kFloatEps = std::numeric_limits<float>::epsilon();
constexpr double kDoubleEps = std::numeric_limits<double>::epsilon();

// ---------------------------------------------------------------------------------------------
// Embree device and error handling

const char* error_name(RTCError code) {
  switch (code) {
    case RTC_ERROR_NONE:
      return "no error";
    case RTC_ERROR_UNKNOWN:
      return "unknown error";
    case RTC_ERROR_INVALID_ARGUMENT:
      return "invalid argument";
    case RTC_ERROR_INVALID_OPERATION:
      return "invalid operation";
    case RTC_ERROR_OUT_OF_MEMORY:
      return "out of memory";
    case RTC_ERROR_UNSUPPORTED_CPU:
      return "unsupported CPU";
    case RTC_ERROR_CANCELLED:
      return "cancelled";
  }
  return "unrecognised error code";
}

/// One Embree device and its scene; the last error message Embree reported is kept so that a
/// failure can be thrown with Embree's own words.
class EmbreeScene {
 public:
  EmbreeScene() {
    device_ = rtcNewDevice(nullptr);
    if (device_ == nullptr) {
      throw std::runtime_error(std::string("embree: cannot create a device: ") +
                               error_name(rtcGetDeviceError(nullptr)));
    }
    rtcSetDeviceErrorFunction(device_, &EmbreeScene::on_error, this);
    scene_ = rtcNewScene(device_);
    if (scene_ == nullptr) {
      const RTCError code = rtcGetDeviceError(device_);
      rtcReleaseDevice(device_);  // the destructor does not run for a failed constructor
      throw std::runtime_error(std::string("embree: cannot create a scene: ") + error_name(code));
    }
  }
  ~EmbreeScene() {
    if (scene_ != nullptr) rtcReleaseScene(scene_);
    if (device_ != nullptr) rtcReleaseDevice(device_);
  }
  EmbreeScene(const EmbreeScene&) = delete;
  EmbreeScene& operator=(const EmbreeScene&) = delete;

  [[nodiscard]] RTCDevice device() const { return device_; }
  [[nodiscard]] RTCScene scene() const { return scene_; }

  /// Throws std::runtime_error if Embree reported an error since the last check.
  void check(const char* what) {
    const RTCError code = rtcGetDeviceError(device_);
    if (code == RTC_ERROR_NONE) return;
    std::string message = std::string("embree: ") + what + ": " + error_name(code);
    const std::lock_guard<std::mutex> lock(message_mutex_);
    if (!last_message_.empty()) message += " (" + last_message_ + ")";
    throw std::runtime_error(message);
  }

 private:
  static void on_error(void* self, RTCError /*code*/, const char* message) {
    auto& scene = *static_cast<EmbreeScene*>(self);
    const std::lock_guard<std::mutex> lock(scene.message_mutex_);  // queries run in parallel
    scene.last_message_ = message != nullptr ? message : "";
  }
  RTCDevice device_ = nullptr;
  RTCScene scene_ = nullptr;
  std::mutex message_mutex_;
  std::string last_message_;
};

/// Owns a geometry until it is attached to a scene (which then holds its own reference).
class GeometryHandle {
 public:
  GeometryHandle(EmbreeScene& embree, RTCGeometryType type)
      : geometry_(rtcNewGeometry(embree.device(), type)) {
    embree.check("creating a geometry");
    if (geometry_ == nullptr) throw std::runtime_error("embree: cannot create a geometry");
  }
  ~GeometryHandle() { rtcReleaseGeometry(geometry_); }
  GeometryHandle(const GeometryHandle&) = delete;
  GeometryHandle& operator=(const GeometryHandle&) = delete;
  [[nodiscard]] RTCGeometry get() const { return geometry_; }

 private:
  RTCGeometry geometry_;
};

/// Largest float <= v and smallest float >= v: box corners rounded outward.
float float_below(double v) {
  auto f = static_cast<float>(v);
  if (static_cast<double>(f) > v) f = std::nextafter(f, -std::numeric_limits<float>::infinity());
  return f;
}
float float_above(double v) {
  auto f = static_cast<float>(v);
  if (static_cast<double>(f) < v) f = std::nextafter(f, std::numeric_limits<float>::infinity());
  return f;
}

// ---------------------------------------------------------------------------------------------
// Triangle geometry in double

/// Closest point to p on triangle abc (Ericson, Real-Time Collision Detection, 5.1.5).
Eigen::Vector3d closest_point_on_triangle(const Eigen::Vector3d& p, const Eigen::Vector3d& a,
                                          const Eigen::Vector3d& b, const Eigen::Vector3d& c) {
  const Eigen::Vector3d ab = b - a, ac = c - a, ap = p - a;
  const double d1 = ab.dot(ap), d2 = ac.dot(ap);
  if (d1 <= 0.0 && d2 <= 0.0) return a;
  const Eigen::Vector3d bp = p - b;
  const double d3 = ab.dot(bp), d4 = ac.dot(bp);
  if (d3 >= 0.0 && d4 <= d3) return b;
  const double vc = d1 * d4 - d3 * d2;
  if (vc <= 0.0 && d1 >= 0.0 && d3 <= 0.0) return a + (d1 / (d1 - d3)) * ab;
  const Eigen::Vector3d cp = p - c;
  const double d5 = ab.dot(cp), d6 = ac.dot(cp);
  if (d6 >= 0.0 && d5 <= d6) return c;
  const double vb = d5 * d2 - d1 * d6;
  if (vb <= 0.0 && d2 >= 0.0 && d6 <= 0.0) return a + (d2 / (d2 - d6)) * ac;
  const double va = d3 * d6 - d5 * d4;
  if (va <= 0.0 && (d4 - d3) >= 0.0 && (d5 - d6) >= 0.0) {
    return b + ((d4 - d3) / ((d4 - d3) + (d5 - d6))) * (c - b);
  }
  const double denom = va + vb + vc;
  if (!(denom > 0.0)) {
    // Degenerate (collinear) triangle: the closest of its three edges.
    Eigen::Vector3d best = a;
    const std::array<std::array<const Eigen::Vector3d*, 2>, 3> edges{
        {{&a, &b}, {&b, &c}, {&c, &a}}};
    for (const auto& e : edges) {
      const Eigen::Vector3d d = *e[1] - *e[0];
      const double len2 = d.squaredNorm();
      const double t = len2 > 0.0 ? std::clamp(d.dot(p - *e[0]) / len2, 0.0, 1.0) : 0.0;
      const Eigen::Vector3d q = *e[0] + t * d;
      if ((q - p).squaredNorm() < (best - p).squaredNorm()) best = q;
    }
    return best;
  }
  return a + (vb / denom) * ab + (vc / denom) * ac;
}

/// Fixed ray directions for the parity test: generic (no two components in a simple ratio), so
/// that rays from points on grid lines or axes do not run along mesh edges or through vertices
/// of axis-aligned meshes.
const std::array<Eigen::Vector3d, 8>& ray_directions() {
  static const std::array<Eigen::Vector3d, 8> directions = [] {
    const std::array<Eigen::Vector3d, 8> raw{{
        {0.5773502691896258, 0.6293203910498375, -0.5206164278273640},
        {-0.3090169943749474, 0.7071067811865476, 0.6363961030678928},
        {0.8090169943749474, -0.3826834323650898, 0.4472135954999579},
        {-0.6180339887498949, -0.5411961001461970, -0.5700953922470480},
        {0.1411200080598672, -0.9092974268256817, 0.3916378471742138},
        {0.9589242746631385, 0.2794154981989259, -0.0495958563958280},
        {-0.7568024953079282, 0.1411200080598672, -0.6377647564194612},
        {0.2588190451025208, 0.4539904997395468, 0.8526401643540922},
    }};
    std::array<Eigen::Vector3d, 8> unit;
    for (std::size_t k = 0; k < raw.size(); ++k) unit[k] = raw[k].normalized();
    return unit;
  }();
  return directions;
}

/// An intersection context that carries the list of hit triangles (Embree passes the context
/// pointer to the filter; it is the first member, so the cast back is well defined).
struct HitCollector {
  RTCIntersectContext context;
  std::vector<unsigned>* hits;
};

void collect_hit(const RTCFilterFunctionNArguments* args) {
  auto* collector = reinterpret_cast<HitCollector*>(args->context);  // NOLINT
  for (unsigned i = 0; i < args->N; ++i) {
    if (args->valid[i] == 0) continue;
    collector->hits->push_back(RTCHitN_primID(args->hit, args->N, i));
    args->valid[i] = 0;  // reject: the traversal goes on and reports every crossing
  }
}

// ---------------------------------------------------------------------------------------------
// Layer cells

constexpr double kXiTolerance = 1e-10;    // a point this far outside a cell (in xi) still counts
constexpr double kClearlyInside = 1e-6;   // no other valid cell can hold such a point
constexpr int kMaxNewtonIterations = 16;  // bilinear maps converge in 2-5 from the centroid

Eigen::Vector3d cell_centroid(int dimension) {
  if (dimension == 1) return {0.5, 0.0, 0.0};
  if (dimension == 2) return {0.5, 0.5, 0.0};
  return {1.0 / 3.0, 1.0 / 3.0, 0.5};
}

/// Smallest signed distance of xi to the faces of the reference cell (>= 0 inside).
double reference_margin(int dimension, const Eigen::Vector3d& xi) {
  if (dimension == 1) return std::min(xi[0], 1.0 - xi[0]);
  if (dimension == 2) return std::min({xi[0], 1.0 - xi[0], xi[1], 1.0 - xi[1]});
  return std::min({xi[0], xi[1], 1.0 - xi[0] - xi[1], xi[2], 1.0 - xi[2]});
}

void no_ray_intersection(const RTCIntersectFunctionNArguments* /*args*/) {}
void no_ray_occlusion(const RTCOccludedFunctionNArguments* /*args*/) {}

}  // namespace

// =============================================================================================
// LayerLocator

struct LayerLocator::Impl {
  int dimension = 3;
  int nodes_per_cell = 6;
  Eigen::Vector3d frame_origin = Eigen::Vector3d::Zero();  // Embree coordinates are relative
  std::vector<RTCBounds> bounds;                           // per cell, Embree frame
  std::vector<double> cell_size;                           // bounding-box diagonal per cell
  std::vector<double> coordinate_scale;                    // largest |x| over the cell's nodes
  /// Each cell's map in closed form (boundary_grid.hpp), which Newton evaluates.
  std::vector<CellMap> maps;
  /// Per cell, 1 where its map is affine (a flat stretch of wall offset by the same vector at
  /// each of its nodes: the cross terms f_j below round-off), and then dx/dxi's inverse (row-major,
  /// unused axes identity): such a cell's point is solved for directly instead of by Newton.
  std::vector<std::uint8_t> affine;
  std::vector<std::array<double, 9>> inverse;
  EmbreeScene embree;

  struct Query {
    const Impl* impl;
    Eigen::Vector3d point;  // unused coordinates 0
    LayerLocator::Location best;
    double best_margin = -kInf;
    bool settled = false;
  };

  explicit Impl(const BoundaryGrid& boundary);
  void set_affine(std::size_t c);
  void try_cell(int c, Query& q) const;
  /// Takes xi (and the map's Jacobian J) as the answer in cell c if it lies in the cell.
  void consider(int c, const double (&xi)[3], const double (&J)[3][3], Query& q) const;
  [[nodiscard]] Location locate(const Eigen::Vector3d& point, int hint) const;

  static bool on_candidate(RTCPointQueryFunctionArguments* args) {
    auto& q = *static_cast<Query*>(args->userPtr);
    if (!q.settled) q.impl->try_cell(static_cast<int>(args->primID), q);
    return false;  // the query sphere (the point) never changes
  }
  static void on_bounds(const RTCBoundsFunctionArguments* args) {
    const auto* self = static_cast<const Impl*>(args->geometryUserPtr);
    *args->bounds_o = self->bounds[args->primID];
  }
};

LayerLocator::Impl::Impl(const BoundaryGrid& boundary) {
  const int dim = boundary.dimension;
  if (dim < 1 || dim > 3) throw std::invalid_argument("LayerLocator: dimension must be 1, 2 or 3");
  if (boundary.nodes.cols() != dim) {
    throw std::invalid_argument("LayerLocator: nodes must have `dimension` columns");
  }
  if (boundary.cells.rows() > 0 && boundary.cells.cols() != boundary.nodes_per_cell()) {
    throw std::invalid_argument("LayerLocator: cells must have 2, 4 or 6 columns (1D, 2D, 3D)");
  }
  if (boundary.cells.size() > 0 &&
      (boundary.cells.minCoeff() < 0 || boundary.cells.maxCoeff() >= boundary.nodes.rows())) {
    throw std::invalid_argument("LayerLocator: a cell refers to a node that does not exist");
  }
  if (!boundary.nodes.allFinite()) {
    throw std::invalid_argument("LayerLocator: node coordinates must be finite");
  }
  dimension = dim;
  nodes_per_cell = boundary.nodes_per_cell();

  const auto cells = static_cast<std::size_t>(boundary.cells.rows());
  if (cells == 0) {
    rtcCommitScene(embree.scene());
    embree.check("building an empty layer scene");
    return;
  }
  for (int i = 0; i < dim; ++i) {
    frame_origin[i] = 0.5 * (boundary.nodes.col(i).minCoeff() + boundary.nodes.col(i).maxCoeff());
  }

  bounds.resize(cells);
  cell_size.resize(cells);
  coordinate_scale.resize(cells);
  maps.resize(cells);
  affine.assign(cells, 0);
  inverse.resize(cells);
  for (std::size_t c = 0; c < cells; ++c) {
    // The basis is a convex combination on the reference cell, so the node box holds the cell.
    Eigen::Vector3d lo = Eigen::Vector3d::Zero(), hi = Eigen::Vector3d::Zero();  // unused: 0
    for (int i = 0; i < dim; ++i) {
      lo[i] = kInf;
      hi[i] = -kInf;
    }
    double scale = 0.0;
    for (int k = 0; k < nodes_per_cell; ++k) {
      const auto x = boundary.nodes.row(boundary.cells(static_cast<Eigen::Index>(c), k));
      for (int i = 0; i < dim; ++i) {
        lo[i] = std::min(lo[i], x(i) - frame_origin[i]);
        hi[i] = std::max(hi[i], x(i) - frame_origin[i]);
        scale = std::max(scale, std::abs(x(i)));
      }
    }
    maps[c] = cell_map(boundary, c);
    const double size = (hi - lo).norm();
    cell_size[c] = size;
    coordinate_scale[c] = scale;
    set_affine(c);
    // Pad: relative to the cell (points within kXiTolerance outside still count), plus a few
    // float steps of the coordinates so that the rounding of the query point cannot miss.
    const double frame_extent = std::max(lo.cwiseAbs().maxCoeff(), hi.cwiseAbs().maxCoeff());
    const double pad = 1e-6 * size + 4.0 * kFloatEps * frame_extent;
    std::array<float, 3> blo{-1.0F, -1.0F, -1.0F}, bhi{1.0F, 1.0F, 1.0F};  // unused axes
    for (int i = 0; i < dim; ++i) {
      blo[static_cast<std::size_t>(i)] = float_below(lo[i] - pad);
      bhi[static_cast<std::size_t>(i)] = float_above(hi[i] + pad);
    }
    RTCBounds& b = bounds[c];
    b.lower_x = blo[0];
    b.lower_y = blo[1];
    b.lower_z = blo[2];
    b.upper_x = bhi[0];
    b.upper_y = bhi[1];
    b.upper_z = bhi[2];
    b.align0 = b.align1 = 0.0F;
  }

  const GeometryHandle handle(embree, RTC_GEOMETRY_TYPE_USER);
  RTCGeometry geometry = handle.get();
  rtcSetGeometryUserPrimitiveCount(geometry, static_cast<unsigned>(cells));
  rtcSetGeometryUserData(geometry, this);
  rtcSetGeometryBoundsFunction(geometry, &Impl::on_bounds, this);
  rtcSetGeometryIntersectFunction(geometry, &no_ray_intersection);
  rtcSetGeometryOccludedFunction(geometry, &no_ray_occlusion);
  rtcCommitGeometry(geometry);
  rtcAttachGeometry(embree.scene(), geometry);
  rtcCommitScene(embree.scene());
  embree.check("building the layer-cell BVH");
}

void LayerLocator::Impl::set_affine(std::size_t c) {
  const CellMap& map = maps[c];
  // Inside the cell the map's residual from its affine part is at most sum_j |f_j| (xi and z
  // lie in [0, 1]): with each component of each f_j below this, the direct answer's residual is
  // below Newton's convergence tolerance (1e-13 of the cell, try_cell()), and Newton from the
  // centroid would stop after one step anyway.
  const double negligible = 1e-14 * cell_size[c];
  for (std::size_t k = 12; k < 18; ++k) {
    if (!(std::abs(map.v[k]) <= negligible)) return;
  }
  // dx/dxi at the cell's origin (the affine part's, the same at every xi), unused axes identity.
  const double origin[3] = {}, zero[3] = {};
  double r[3], dx[3][3];
  map.evaluate(origin, zero, r, dx);
  Eigen::Matrix3d J = Eigen::Matrix3d::Identity();
  for (int i = 0; i < dimension; ++i) {
    for (int j = 0; j < dimension; ++j) J(i, j) = dx[i][j];
  }
  const double det = J.determinant();
  if (!(std::abs(det) > 0.0) || !std::isfinite(det)) return;  // Newton says why it fails
  const Eigen::Matrix3d inv = J.inverse();
  for (int i = 0; i < 3; ++i) {
    for (int j = 0; j < 3; ++j) inverse[c][static_cast<std::size_t>(3 * i + j)] = inv(i, j);
  }
  affine[c] = 1;
}

void LayerLocator::Impl::consider(int c, const double (&xi)[3], const double (&J)[3][3],
                                  Query& q) const {
  const Eigen::Vector3d solution(xi[0], xi[1], xi[2]);  // unused entries stay 0
  const double margin = reference_margin(dimension, solution);
  if (margin < -kXiTolerance) return;
  // Best margin wins, ties to the lower index: independent of the order Embree reports cells.
  if (margin > q.best_margin || (margin == q.best_margin && c < q.best.cell)) {
    q.best_margin = margin;
    q.best.cell = c;
    q.best.xi = solution;
    for (int i = 0; i < 3; ++i) {
      for (int j = 0; j < 3; ++j) q.best.jacobian(i, j) = J[i][j];  // at xi: unused entries 0
    }
  }
  if (margin > kClearlyInside) q.settled = true;
}

void LayerLocator::Impl::try_cell(int c, Query& q) const {
  const int dim = dimension;
  const auto cell = static_cast<std::size_t>(c);
  if (affine[cell] != 0) {
    // xi = J^-1 (p - x(0)) (unused axes: identity in the inverse); the Jacobian handed on is
    // the map's at xi, as Newton's is (rows and columns beyond `dimension` 0).
    const CellMap& map = maps[cell];
    const std::array<double, 9>& inv = inverse[cell];
    const double d[3] = {q.point[0] - map.v[0], q.point[1] - map.v[1], q.point[2] - map.v[2]};
    double xi[3] = {};
    for (int i = 0; i < dim; ++i) {
      xi[i] = inv[3 * i] * d[0] + inv[3 * i + 1] * d[1] + inv[3 * i + 2] * d[2];
    }
    const double point[3] = {q.point[0], q.point[1], q.point[2]};
    double r[3], J[3][3];
    map.evaluate(xi, point, r, J);
    consider(c, xi, J, q);
    return;
  }
  // |x(xi) - p| below this is converged: 1e-13 of the cell, or round-off of the coordinates.
  const double tolerance =
      1e-13 * cell_size[cell] +
      16.0 * kDoubleEps * std::max(coordinate_scale[cell], q.point.cwiseAbs().maxCoeff());
  const CellMap& map = maps[cell];
  // Plain scalars below: Eigen's small fixed-size temporaries here went through the stack and
  // cost more than the arithmetic (store-forwarding stalls).
  double xi[3] = {};
  const Eigen::Vector3d start = cell_centroid(dim);
  for (int i = 0; i < 3; ++i) xi[i] = start[i];
  const double point[3] = {q.point[0], q.point[1], q.point[2]};
  bool converged = false;
  double J[3][3];
  for (int iteration = 0; iteration < kMaxNewtonIterations; ++iteration) {
    double r[3];
    map.evaluate(xi, point, r, J);
    if (r[0] * r[0] + r[1] * r[1] + r[2] * r[2] < tolerance * tolerance) {
      converged = true;
      break;
    }
    for (int i = dim; i < 3; ++i) J[i][i] = 1.0;  // unused axes
    // xi -= J^-1 r by Cramer's rule (cofactors of the 3 x 3 Jacobian).
    const double c00 = J[1][1] * J[2][2] - J[1][2] * J[2][1];
    const double c01 = J[1][2] * J[2][0] - J[1][0] * J[2][2];
    const double c02 = J[1][0] * J[2][1] - J[1][1] * J[2][0];
    const double det = J[0][0] * c00 + J[0][1] * c01 + J[0][2] * c02;
    if (!(std::abs(det) > 0.0) || !std::isfinite(det)) return;
    const double inv = 1.0 / det;
    const double d0 = inv * (c00 * r[0] + (J[0][2] * J[2][1] - J[0][1] * J[2][2]) * r[1] +
                             (J[0][1] * J[1][2] - J[0][2] * J[1][1]) * r[2]);
    const double d1 = inv * (c01 * r[0] + (J[0][0] * J[2][2] - J[0][2] * J[2][0]) * r[1] +
                             (J[0][2] * J[1][0] - J[0][0] * J[1][2]) * r[2]);
    const double d2 = inv * (c02 * r[0] + (J[0][1] * J[2][0] - J[0][0] * J[2][1]) * r[1] +
                             (J[0][0] * J[1][1] - J[0][1] * J[1][0]) * r[2]);
    xi[0] -= d0;
    xi[1] -= d1;
    xi[2] -= d2;
    // A point far outside the cell: Newton may wander off; it is not in this cell anyway.
    if (!(std::max({std::abs(xi[0]), std::abs(xi[1]), std::abs(xi[2])}) < 4.0)) return;
  }
  if (!converged) return;
  consider(c, xi, J, q);
}

LayerLocator::Location LayerLocator::Impl::locate(const Eigen::Vector3d& point, int hint) const {
  Query q{this, Eigen::Vector3d::Zero(), {}, -kInf, false};
  if (bounds.empty()) return q.best;
  const int dim = dimension;
  for (int i = 0; i < dim; ++i) q.point[i] = point[i];
  if (!q.point.allFinite()) return q.best;
  if (hint >= 0 && hint < static_cast<int>(bounds.size())) {
    try_cell(hint, q);
    if (q.settled) return q.best;  // clearly inside: no other cell holds the point
  }
  RTCPointQuery query;
  const Eigen::Vector3d local = q.point - frame_origin;
  query.x = dim > 0 ? static_cast<float>(local[0]) : 0.0F;
  query.y = dim > 1 ? static_cast<float>(local[1]) : 0.0F;
  query.z = dim > 2 ? static_cast<float>(local[2]) : 0.0F;
  query.radius = 0.0F;  // the boxes that contain the point
  query.time = 0.0F;
  RTCPointQueryContext context;
  rtcInitPointQueryContext(&context);
  rtcPointQuery(embree.scene(), &query, &context, &Impl::on_candidate, &q);
  return q.best;
}

LayerLocator::LayerLocator(const BoundaryGrid& boundary)
    : impl_(std::make_unique<Impl>(boundary)) {}
LayerLocator::~LayerLocator() = default;
LayerLocator::LayerLocator(LayerLocator&&) noexcept = default;
LayerLocator& LayerLocator::operator=(LayerLocator&&) noexcept = default;

LayerLocator::Location LayerLocator::locate(const Eigen::Vector3d& point, int hint) const {
  return impl_->locate(point, hint);
}

void LayerLocator::prefetch(int cell) const noexcept {
  const auto c = static_cast<std::size_t>(cell);
  if (cell < 0 || c >= impl_->maps.size()) return;
  const auto* map = reinterpret_cast<const char*>(&impl_->maps[c]);
  for (std::size_t line = 0; line < sizeof(CellMap); line += 64) __builtin_prefetch(map + line);
  __builtin_prefetch(impl_->inverse[c].data());
  __builtin_prefetch(&impl_->affine[c]);
}

void LayerLocator::locate(const Eigen::MatrixXd& points, std::vector<Location>& out,
                          const std::vector<std::uint8_t>* skip) const {
  const int dim = impl_->dimension;
  if (points.rows() > 0 && points.cols() != dim) {
    throw std::invalid_argument("LayerLocator::locate: points must have `dimension` columns");
  }
  const auto count = static_cast<std::size_t>(points.rows());
  if (skip != nullptr && skip->size() != count) {
    throw std::invalid_argument("LayerLocator::locate: skip must have one flag per point");
  }
  out.assign(count, Location{});
  tbb::parallel_for(tbb::blocked_range<std::size_t>(0, count, 256),
                    [&](const tbb::blocked_range<std::size_t>& range) {
                      Eigen::Vector3d p = Eigen::Vector3d::Zero();
                      for (std::size_t i = range.begin(); i != range.end(); ++i) {
                        if (skip != nullptr && (*skip)[i] != 0) continue;
                        const auto row = static_cast<Eigen::Index>(i);
                        for (int k = 0; k < dim; ++k) p[k] = points(row, k);
                        out[i] = impl_->locate(p, -1);
                      }
                    });
}

// =============================================================================================
// ClosedSurface

struct ClosedSurface::Impl {
  Eigen::MatrixX3d V;  // relative to frame_origin
  Eigen::MatrixX3i F;
  Eigen::Vector3d frame_origin = Eigen::Vector3d::Zero();
  double diagonal = 0.0;
  double edge_margin = 0.0;  // rays closer than this to an edge are cast again
  double ray_backoff = 0.0;  // rays start this far behind the point (float round-off of t)
  EmbreeScene embree;

  explicit Impl(const TriangleMesh& mesh);

  enum class Crossing { miss, ahead, behind, ambiguous };
  [[nodiscard]] Crossing classify(int f, const Eigen::Vector3d& p, const Eigen::Vector3d& d) const;
  [[nodiscard]] bool inside(const Eigen::Vector3d& point) const;
  [[nodiscard]] double winding_number(const Eigen::Vector3d& p) const;
  [[nodiscard]] double distance(const Eigen::Vector3d& point, Eigen::Vector3d* closest,
                                int* facet) const;

  struct ClosestQuery {
    const Impl* impl;
    Eigen::Vector3d point;  // Embree frame, double
    double best_distance = kInf;
    Eigen::Vector3d best_point = Eigen::Vector3d::Zero();
    double float_slack = 0.0;
    int best_facet = -1;
  };
  static bool on_closest_candidate(RTCPointQueryFunctionArguments* args);
};

ClosedSurface::Impl::Impl(const TriangleMesh& mesh) {
  if (mesh.F.rows() == 0 || mesh.V.rows() == 0) {
    throw std::invalid_argument("ClosedSurface: the mesh has no triangles");
  }
  if (mesh.F.minCoeff() < 0 || mesh.F.maxCoeff() >= mesh.V.rows()) {
    throw std::invalid_argument("ClosedSurface: a face refers to a vertex that does not exist");
  }
  if (!mesh.V.allFinite()) {
    throw std::invalid_argument("ClosedSurface: vertex coordinates must be finite");
  }
  const Eigen::Vector3d lo = mesh.V.colwise().minCoeff().transpose();
  const Eigen::Vector3d hi = mesh.V.colwise().maxCoeff().transpose();
  frame_origin = 0.5 * (lo + hi);
  diagonal = (hi - lo).norm();
  V = mesh.V.rowwise() - frame_origin.transpose();
  F = mesh.F;
  // Embree's float edge tests err by a few float steps of the frame coordinates; 4e-6 of the
  // diagonal is ~30 of them, so a crossing Embree might have missed is always seen as ambiguous.
  edge_margin = 4e-6 * diagonal;
  ray_backoff = 1e-3 * diagonal;

  rtcSetSceneFlags(embree.scene(), RTC_SCENE_FLAG_ROBUST);
  const GeometryHandle handle(embree, RTC_GEOMETRY_TYPE_TRIANGLE);
  RTCGeometry geometry = handle.get();
  auto* vertices = static_cast<float*>(rtcSetNewGeometryBuffer(geometry, RTC_BUFFER_TYPE_VERTEX, 0,
                                                               RTC_FORMAT_FLOAT3, 3 * sizeof(float),
                                                               static_cast<std::size_t>(V.rows())));
  auto* indices = static_cast<unsigned*>(
      rtcSetNewGeometryBuffer(geometry, RTC_BUFFER_TYPE_INDEX, 0, RTC_FORMAT_UINT3,
                              3 * sizeof(unsigned), static_cast<std::size_t>(F.rows())));
  embree.check("allocating the triangle buffers");
  if (vertices == nullptr || indices == nullptr) {
    throw std::runtime_error("embree: cannot allocate the triangle buffers");
  }
  for (Eigen::Index v = 0; v < V.rows(); ++v) {
    for (int i = 0; i < 3; ++i) vertices[3 * v + i] = static_cast<float>(V(v, i));
  }
  for (Eigen::Index f = 0; f < F.rows(); ++f) {
    for (int i = 0; i < 3; ++i) indices[3 * f + i] = static_cast<unsigned>(F(f, i));
  }
  rtcSetGeometryIntersectFilterFunction(geometry, &collect_hit);
  rtcCommitGeometry(geometry);
  rtcAttachGeometry(embree.scene(), geometry);
  rtcCommitScene(embree.scene());
  embree.check("building the triangle BVH");
}

ClosedSurface::Impl::Crossing ClosedSurface::Impl::classify(int f, const Eigen::Vector3d& p,
                                                            const Eigen::Vector3d& d) const {
  const Eigen::Vector3d a = V.row(F(f, 0)).transpose();
  const Eigen::Vector3d b = V.row(F(f, 1)).transpose();
  const Eigen::Vector3d c = V.row(F(f, 2)).transpose();
  const Eigen::Vector3d pa = a - p, pb = b - p, pc = c - p;
  // Pluecker edge functions: which side of each edge the ray passes. Swapping an edge's ends
  // negates the value exactly, so the two triangles of a shared edge never disagree.
  const std::array<double, 3> side{d.dot(pa.cross(pb)), d.dot(pb.cross(pc)), d.dot(pc.cross(pa))};
  const std::array<double, 3> reach{edge_margin * (b - a).norm(), edge_margin * (c - b).norm(),
                                    edge_margin * (a - c).norm()};
  bool clear_positive = false, clear_negative = false, near_edge = false;
  for (std::size_t e = 0; e < 3; ++e) {
    if (side[e] > reach[e]) {
      clear_positive = true;
    } else if (side[e] < -reach[e]) {
      clear_negative = true;
    } else {
      near_edge = true;
    }
  }
  if (clear_positive && clear_negative) return Crossing::miss;  // clearly beside an edge
  if (near_edge) return Crossing::ambiguous;                    // through an edge or vertex
  // The ray crosses the interior; is the crossing ahead of the point? t = n.(a-p) / n.d.
  const Eigen::Vector3d n = (b - a).cross(c - a);
  const double height = n.dot(pa);
  const double height_error =
      32.0 * kDoubleEps * n.norm() * std::max({pa.norm(), pb.norm(), pc.norm()});
  if (std::abs(height) <= height_error) return Crossing::ambiguous;  // point on the face
  const double along = side[0] + side[1] + side[2];                  // = n.d, sign known
  return (height > 0.0) == (along > 0.0) ? Crossing::ahead : Crossing::behind;
}

double ClosedSurface::Impl::winding_number(const Eigen::Vector3d& p) const {
  // Van Oosterom and Strackee (1983): solid angle of each triangle seen from p.
  double solid_angle = 0.0;
  for (Eigen::Index f = 0; f < F.rows(); ++f) {
    const Eigen::Vector3d a = V.row(F(f, 0)).transpose() - p;
    const Eigen::Vector3d b = V.row(F(f, 1)).transpose() - p;
    const Eigen::Vector3d c = V.row(F(f, 2)).transpose() - p;
    const double la = a.norm(), lb = b.norm(), lc = c.norm();
    const double numerator = a.dot(b.cross(c));
    const double denominator = la * lb * lc + a.dot(b) * lc + a.dot(c) * lb + b.dot(c) * la;
    solid_angle += 2.0 * std::atan2(numerator, denominator);
  }
  return solid_angle / (4.0 * std::numbers::pi);
}

bool ClosedSurface::Impl::inside(const Eigen::Vector3d& point) const {
  if (!point.allFinite()) return false;
  const Eigen::Vector3d p = point - frame_origin;
  thread_local std::vector<unsigned> hits;
  for (const Eigen::Vector3d& d : ray_directions()) {
    hits.clear();
    HitCollector collector{};
    rtcInitIntersectContext(&collector.context);
    collector.hits = &hits;
    const Eigen::Vector3d origin = p - ray_backoff * d;
    RTCRayHit rayhit{};
    rayhit.ray.org_x = static_cast<float>(origin[0]);
    rayhit.ray.org_y = static_cast<float>(origin[1]);
    rayhit.ray.org_z = static_cast<float>(origin[2]);
    rayhit.ray.dir_x = static_cast<float>(d[0]);
    rayhit.ray.dir_y = static_cast<float>(d[1]);
    rayhit.ray.dir_z = static_cast<float>(d[2]);
    rayhit.ray.tnear = 0.0F;
    rayhit.ray.tfar = std::numeric_limits<float>::infinity();
    rayhit.ray.mask = 0xFFFFFFFFU;
    rayhit.ray.flags = 0;
    rayhit.hit.geomID = RTC_INVALID_GEOMETRY_ID;
    rtcIntersect1(embree.scene(), &collector.context, &rayhit);
    // A triangle split over several BVH leaves can be reported more than once.
    std::sort(hits.begin(), hits.end());
    hits.erase(std::unique(hits.begin(), hits.end()), hits.end());
    bool ambiguous = false;
    int crossings = 0;
    for (const unsigned f : hits) {
      const Crossing crossing = classify(static_cast<int>(f), p, d);
      if (crossing == Crossing::ambiguous) {
        ambiguous = true;
        break;
      }
      if (crossing == Crossing::ahead) ++crossings;
    }
    if (!ambiguous) return (crossings % 2) == 1;
  }
  // Every direction grazed an edge or the point lies on the surface: count solid angles.
  return std::abs(winding_number(p)) >= 0.5;
}

bool ClosedSurface::Impl::on_closest_candidate(RTCPointQueryFunctionArguments* args) {
  auto& q = *static_cast<ClosestQuery*>(args->userPtr);
  const Impl& self = *q.impl;
  const auto f = static_cast<Eigen::Index>(args->primID);
  const Eigen::Vector3d x = closest_point_on_triangle(q.point, self.V.row(self.F(f, 0)).transpose(),
                                                      self.V.row(self.F(f, 1)).transpose(),
                                                      self.V.row(self.F(f, 2)).transpose());
  const double distance = (x - q.point).norm();
  if (!(distance < q.best_distance)) return false;
  q.best_distance = distance;
  q.best_point = x;
  q.best_facet = static_cast<int>(f);
  // Shrink the search sphere, kept a little larger so that the float query point and boxes
  // cannot cut off a triangle that is closer in double.
  args->query->radius = float_above(distance + q.float_slack + 2.0 * kFloatEps * distance);
  return true;
}

double ClosedSurface::Impl::distance(const Eigen::Vector3d& point, Eigen::Vector3d* closest,
                                     int* facet) const {
  if (facet != nullptr) *facet = -1;
  if (!point.allFinite()) {
    if (closest != nullptr) closest->setConstant(std::numeric_limits<double>::quiet_NaN());
    return std::numeric_limits<double>::quiet_NaN();
  }
  ClosestQuery q{this, point - frame_origin, kInf, Eigen::Vector3d::Zero(), 0.0, -1};
  q.float_slack = 4.0 * kFloatEps * (q.point.cwiseAbs().maxCoeff() + diagonal);
  RTCPointQuery query;
  query.x = static_cast<float>(q.point[0]);
  query.y = static_cast<float>(q.point[1]);
  query.z = static_cast<float>(q.point[2]);
  query.radius = std::numeric_limits<float>::infinity();
  query.time = 0.0F;
  RTCPointQueryContext context;
  rtcInitPointQueryContext(&context);
  rtcPointQuery(embree.scene(), &query, &context, &Impl::on_closest_candidate, &q);
  if (closest != nullptr) *closest = q.best_point + frame_origin;
  if (facet != nullptr) *facet = q.best_facet;
  return q.best_distance;
}

ClosedSurface::ClosedSurface(const TriangleMesh& mesh) : impl_(std::make_unique<Impl>(mesh)) {}
ClosedSurface::~ClosedSurface() = default;
ClosedSurface::ClosedSurface(ClosedSurface&&) noexcept = default;
ClosedSurface& ClosedSurface::operator=(ClosedSurface&&) noexcept = default;

bool ClosedSurface::inside(const Eigen::Vector3d& point) const { return impl_->inside(point); }

double ClosedSurface::signed_distance(const Eigen::Vector3d& point) const {
  const double d = impl_->distance(point, nullptr, nullptr);
  return impl_->inside(point) ? -d : d;
}

double ClosedSurface::distance(const Eigen::Vector3d& point, Eigen::Vector3d* closest,
                               int* facet) const {
  return impl_->distance(point, closest, facet);
}

void ClosedSurface::inside(const Eigen::MatrixX3d& points, std::vector<std::uint8_t>& out) const {
  const auto count = static_cast<std::size_t>(points.rows());
  out.assign(count, 0);
  tbb::parallel_for(tbb::blocked_range<std::size_t>(0, count, 256),
                    [&](const tbb::blocked_range<std::size_t>& range) {
                      for (std::size_t i = range.begin(); i != range.end(); ++i) {
                        const auto row = static_cast<Eigen::Index>(i);
                        out[i] = impl_->inside(points.row(row).transpose()) ? 1 : 0;
                      }
                    });
}

Eigen::Vector3d ClosedSurface::ray_direction(int k) {
  const auto& directions = ray_directions();
  if (k < 0 || k >= static_cast<int>(directions.size())) {
    throw std::out_of_range("ClosedSurface::ray_direction: no such direction");
  }
  return directions[static_cast<std::size_t>(k)];
}

int ClosedSurface::ray_direction_count() { return static_cast<int>(ray_directions().size()); }

// =============================================================================================
// Free functions

double distance_to_surface(const TriangleMesh& mesh, const Eigen::Vector3d& point,
                           Eigen::Vector3d* closest) {
  if (mesh.F.rows() == 0) throw std::invalid_argument("distance_to_surface: no triangles");
  if (mesh.F.minCoeff() < 0 || mesh.F.maxCoeff() >= mesh.V.rows()) {
    throw std::invalid_argument("distance_to_surface: a face refers to a missing vertex");
  }
  // One point: a linear scan in double is cheaper than building a BVH (O(F) vs O(F log F)).
  // Many points: build a ClosedSurface once and call distance(), which uses the Embree BVH.
  double best = kInf;
  Eigen::Vector3d best_point = Eigen::Vector3d::Zero();
  for (Eigen::Index f = 0; f < mesh.F.rows(); ++f) {
    const Eigen::Vector3d x = closest_point_on_triangle(point, mesh.V.row(mesh.F(f, 0)).transpose(),
                                                        mesh.V.row(mesh.F(f, 1)).transpose(),
                                                        mesh.V.row(mesh.F(f, 2)).transpose());
    const double d = (x - point).norm();
    if (d < best) {
      best = d;
      best_point = x;
    }
  }
  if (closest != nullptr) *closest = best_point;
  return best;
}

Eigen::MatrixX3d fill_closed_surface(const TriangleMesh& mesh, const Eigen::Vector3d& origin,
                                     double spacing, int particles_per_cell) {
  if (!(spacing > 0.0) || !std::isfinite(spacing)) {
    throw std::invalid_argument("fill_closed_surface: spacing must be finite and > 0");
  }
  if (particles_per_cell < 1) {
    throw std::invalid_argument("fill_closed_surface: particles_per_cell must be >= 1");
  }
  if (!origin.allFinite()) throw std::invalid_argument("fill_closed_surface: origin not finite");
  const ClosedSurface surface(mesh);
  // Sub-cell centres: origin + step (m + 1/2) for integer m, step = h / n.
  const double step = spacing / particles_per_cell;
  const Eigen::Vector3d lo = mesh.V.colwise().minCoeff().transpose();
  const Eigen::Vector3d hi = mesh.V.colwise().maxCoeff().transpose();
  std::array<long, 3> first_index{}, count{};
  for (int i = 0; i < 3; ++i) {
    const double m_lo = std::ceil((lo[i] - origin[i]) / step - 0.5);
    const double m_hi = std::floor((hi[i] - origin[i]) / step - 0.5);
    first_index[static_cast<std::size_t>(i)] = static_cast<long>(m_lo);
    count[static_cast<std::size_t>(i)] = std::max(0L, static_cast<long>(m_hi - m_lo) + 1);
  }
  const auto centre = [&](int axis, long m) {
    return origin[axis] +
           step * (static_cast<double>(first_index[static_cast<std::size_t>(axis)] + m) + 0.5);
  };
  // One z-slab per task; slabs are concatenated in order, so the output is deterministic.
  std::vector<std::vector<Eigen::Vector3d>> slabs(static_cast<std::size_t>(count[2]));
  tbb::parallel_for(tbb::blocked_range<long>(0, count[2]), [&](const tbb::blocked_range<long>& r) {
    for (long k = r.begin(); k != r.end(); ++k) {
      auto& slab = slabs[static_cast<std::size_t>(k)];
      for (long j = 0; j < count[1]; ++j) {
        for (long i = 0; i < count[0]; ++i) {
          const Eigen::Vector3d x(centre(0, i), centre(1, j), centre(2, k));
          if (surface.inside(x)) slab.push_back(x);
        }
      }
    }
  });
  std::size_t total = 0;
  for (const auto& slab : slabs) total += slab.size();
  Eigen::MatrixX3d particles(static_cast<Eigen::Index>(total), 3);
  Eigen::Index row = 0;
  for (const auto& slab : slabs) {
    for (const auto& x : slab) particles.row(row++) = x.transpose();
  }
  return particles;
}

}  // namespace mpmgeom
