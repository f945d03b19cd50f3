// Point queries: which layer cell holds a point (and where), inside/outside of closed surfaces,
// signed distance, filling a closed surface with particles. Embree inside, plain arrays out.
#pragma once

#include <cstdint>
#include <memory>
#include <vector>

#include <Eigen/Core>

#include "mpmgeom/boundary_grid.hpp"

namespace mpmgeom {

/// Finds the layer cell containing each point and its natural coordinates (Embree BVH over
/// the cell bounds for candidates, Newton on the isoparametric map in double for xi).
///
/// A point counts as inside a cell when its natural coordinates are within 1e-10 of the
/// reference cell (boundary_grid.hpp), so points on the faces of the layer are found. A point on
/// a face shared by two cells gets one of them: the cell it is deepest inside (the largest
/// smallest distance of xi to the reference faces), ties to the lower cell index, the same for
/// every call. Assumes a valid layer (cells that do not overlap, positive Jacobians). The
/// locator copies what it needs from `boundary`; it does not keep a reference.
class LayerLocator {
 public:
  struct Location {
    int cell = -1;                                 ///< -1: not in the layer
    Eigen::Vector3d xi = Eigen::Vector3d::Zero();  ///< natural coordinates in `cell` (unused 0)
    /// dx/dxi of the cell's map at xi (the top-left dimension x dimension block; the rest 0),
    /// for the basis gradients: Newton formed it at the answer.
    Eigen::Matrix3d jacobian = Eigen::Matrix3d::Zero();
  };
  /// Throws std::invalid_argument for inconsistent arrays, std::runtime_error if Embree fails.
  explicit LayerLocator(const BoundaryGrid& boundary);
  ~LayerLocator();
  LayerLocator(const LayerLocator&) = delete;
  LayerLocator& operator=(const LayerLocator&) = delete;
  LayerLocator(LayerLocator&&) noexcept;  ///< a moved-from locator may only be destroyed
  LayerLocator& operator=(LayerLocator&&) noexcept;

  /// `point`: the first `dimension` entries are used. Thread-safe. `hint`: a cell to try first
  /// (a particle's cell of the step before); a point clearly inside it is in no other cell, so
  /// the answer is the same as without it, found without the Embree query.
  [[nodiscard]] Location locate(const Eigen::Vector3d& point, int hint = -1) const;
  /// Asks the memory system for what locate() reads of `cell` as a hint (a caller that knows
  /// its next queries' hints issues this a few queries ahead; no effect on any answer).
  void prefetch(int cell) const noexcept;
  /// points: #P x dimension. Parallel (TBB). `skip` (optional, #P): 1 = do not query (the point
  /// is known to be outside the layer, e.g. from layer_cell_flags), result cell -1.
  void locate(const Eigen::MatrixXd& points, std::vector<Location>& out,
              const std::vector<std::uint8_t>* skip = nullptr) const;

 private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
};

/// Inside/outside and signed distance for a closed, consistently oriented surface.
///
/// `inside` counts ray crossings (parity), decided in double: Embree (float) only collects the
/// triangles a ray may cross. A ray passing within ~4e-6 of the bounding-box diagonal of an edge
/// or vertex, grazing a face, or starting on a face is discarded and cast again in the next of
/// a few fixed directions; if all are discarded the generalized winding number decides. Points
/// on the surface (to round-off) may be reported either way. All queries are thread-safe.
class ClosedSurface {
 public:
  /// Throws std::invalid_argument for an empty or inconsistent mesh, std::runtime_error if
  /// Embree fails. Closedness is not checked (distance() works for any mesh).
  explicit ClosedSurface(const TriangleMesh& mesh);
  ~ClosedSurface();
  ClosedSurface(const ClosedSurface&) = delete;
  ClosedSurface& operator=(const ClosedSurface&) = delete;
  ClosedSurface(ClosedSurface&&) noexcept;  ///< a moved-from surface may only be destroyed
  ClosedSurface& operator=(ClosedSurface&&) noexcept;

  /// Ray parity with several ray directions (robust to rays grazing edges and vertices).
  [[nodiscard]] bool inside(const Eigen::Vector3d& point) const;
  /// Negative inside, positive outside, magnitude = distance to the surface.
  [[nodiscard]] double signed_distance(const Eigen::Vector3d& point) const;
  /// Unsigned distance to the triangles (closed or not) and optionally the closest point and
  /// the triangle it lies on (Embree point query, exact point-triangle distance in double).
  [[nodiscard]] double distance(const Eigen::Vector3d& point, Eigen::Vector3d* closest = nullptr,
                                int* facet = nullptr) const;
  void inside(const Eigen::MatrixX3d& points, std::vector<std::uint8_t>& out) const;  ///< TBB

  /// The fixed ray directions `inside` tries in turn (unit vectors). Public so that tests can
  /// aim rays exactly at edges and vertices.
  [[nodiscard]] static Eigen::Vector3d ray_direction(int k);
  [[nodiscard]] static int ray_direction_count();

 private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
};

/// Unsigned distance from a point to a (possibly open) surface, and the closest point. A linear
/// scan in double, cheaper than building a BVH for one point; for many points build a
/// ClosedSurface once and call its distance().
double distance_to_surface(const TriangleMesh& mesh, const Eigen::Vector3d& point,
                           Eigen::Vector3d* closest = nullptr);

/// Particle positions filling a closed surface: n per cell per direction at the sub-cell
/// centres of the grid (origin, spacing h) that fall inside, i.e. origin + h/n (m + 1/2) for
/// integer m, within the bounding box of the mesh. #P x 3, ordered z-slab by z-slab, then y,
/// then x (deterministic).
Eigen::MatrixX3d fill_closed_surface(const TriangleMesh& mesh, const Eigen::Vector3d& origin,
                                     double spacing, int particles_per_cell);

}  // namespace mpmgeom
