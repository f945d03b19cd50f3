// The signed-distance wall, the baseline the dual-grid walls are measured against (DESIGN.md
// section 4, "Baselines"): the wall is a level set on the standard grid. Every node within
// kernel reach behind the surface (signed distance phi <= 0) is constrained like a box-wall
// node, in its own frame: the normal is the direction from the closest surface point to the
// node, oriented into the material (the facet normal where the node is on the surface). Slip,
// stick and Coulomb friction, separable or bonded, as for the other walls; the change of nodal
// momentum is the wall force.
//
// The surface is the wall face Gamma of the same layer the dual-grid walls build (so the mesh is
// imported, repaired and remeshed the same way); its facets are oriented into the material.

#include <cmath>

#include <tbb/parallel_for.h>

#include "mpm/solver.hpp"
#include "mpmgeom/locator.hpp"

namespace mpm {
namespace {

/// Closest point on segment [a, b] to x.
Eigen::Vector2d closest_on_segment(const Eigen::Vector2d& x, const Eigen::Vector2d& a,
                                   const Eigen::Vector2d& b) {
  const Eigen::Vector2d ab = b - a;
  const double len2 = ab.squaredNorm();
  const double s = len2 > 0.0 ? std::clamp((x - a).dot(ab) / len2, 0.0, 1.0) : 0.0;
  return a + s * ab;
}

}  // namespace

template <int D>
void Solver<D>::setup_sdf_wall(const DualWallSpec& spec) {
  const mpmgeom::BoundaryGrid& layer = spec.package->layer;
  const double reach = 2.0 * grid.h;  // nodes deeper than the widest kernel never get mass
  SdfWall wall;
  wall.spec = &spec;
  wall.impulse = static_cast<int>(wall_impulse_.size());
  wall_impulse_.emplace_back(Eigen::Vector3d::Zero());

  // Signed distance and normal into the material at a point, per dimension.
  std::unique_ptr<mpmgeom::ClosedSurface> surface;
  std::vector<Eigen::Vector3d> facet_normal;
  if constexpr (D == 3) {
    mpmgeom::TriangleMesh mesh;
    mesh.V = layer.nodes;
    mesh.F = layer.wall_facets;
    surface = std::make_unique<mpmgeom::ClosedSurface>(mesh);
    for (Eigen::Index f = 0; f < mesh.F.rows(); ++f) {
      const Eigen::Vector3d a = mesh.V.row(mesh.F(f, 0)), b = mesh.V.row(mesh.F(f, 1)),
                            c = mesh.V.row(mesh.F(f, 2));
      facet_normal.push_back((b - a).cross(c - a).normalized());
    }
  }
  auto probe = [&](const Vec<D>& x, Vec<D>& normal) {
    Vec<D> closest;
    Vec<D> facet_n;
    if constexpr (D == 1) {
      closest = layer.nodes.row(layer.wall_facets(0, 0)).transpose();
      facet_n = layer.node_normals.row(layer.wall_facets(0, 0)).transpose();
    } else if constexpr (D == 2) {
      double best = std::numeric_limits<double>::infinity();
      for (Eigen::Index f = 0; f < layer.wall_facets.rows(); ++f) {
        const Eigen::Vector2d a = layer.nodes.row(layer.wall_facets(f, 0)).transpose();
        const Eigen::Vector2d b = layer.nodes.row(layer.wall_facets(f, 1)).transpose();
        const Eigen::Vector2d c = closest_on_segment(x, a, b);
        const double d = (x - c).squaredNorm();
        if (d < best) {
          best = d;
          closest = c;
          facet_n = Eigen::Vector2d(-(b - a).y(), (b - a).x()).normalized();
        }
      }
    } else {
      int facet = -1;
      Eigen::Vector3d c;
      const double unsigned_distance = surface->distance(x, &c, &facet);
      static_cast<void>(unsigned_distance);  // recomputed below with its sign
      closest = c;
      facet_n = facet_normal[static_cast<std::size_t>(facet)];
    }
    const Vec<D> offset = x - closest;
    const double side = offset.dot(facet_n) >= 0.0 ? 1.0 : -1.0;
    const double dist = offset.norm();
    normal = dist > 1e-9 * grid.h ? Vec<D>(side * offset / dist) : facet_n;
    return side * dist;
  };

  std::vector<char> behind(grid.size(), 0);
  std::vector<Vec<D>> normals(grid.size());
  tbb::parallel_for(std::size_t{0}, grid.size(), [&](std::size_t n) {
    const Index<D> i = grid.multi(static_cast<int>(n));
    if (!grid.in_box(i)) return;
    const Vec<D> x = grid.position(i);
    Vec<D> normal;
    const double phi = probe(x, normal);
    if (phi <= 0.0 && phi >= -reach) {
      behind[n] = 1;
      normals[n] = normal;
    }
  });
  for (std::size_t n = 0; n < grid.size(); ++n) {
    if (behind[n] == 0) continue;
    wall.nodes.push_back(static_cast<int>(n));
    wall.normal.push_back(normals[n]);
  }
  sdf_.push_back(std::move(wall));
}

template <int D>
void Solver<D>::constrain_sdf_walls(NodeField<Vec<D>>& velocity, bool record) {
  for (const SdfWall& wall : sdf_) {
    Vec<D> impulse = Vec<D>::Zero();
    std::visit(
        [&](const auto& condition) {
          for (std::size_t i = 0; i < wall.nodes.size(); ++i) {
            const int n = wall.nodes[i];
            const double m = grid.mass[n];
            if (m <= mass_threshold_) continue;
            const Vec<D> before = velocity[n];
            velocity[n] = constrain_velocity<D>(condition, wall.spec->contact.separable,
                                                wall.normal[i], before);
            impulse += m * (velocity[n] - before);
          }
        },
        wall.spec->contact.condition);
    if (record) wall_impulse_[wall.impulse] += pad3<D>(impulse);
  }
}

#define MPM_SDF_MEMBERS(D)                                      \
  template void Solver<D>::setup_sdf_wall(const DualWallSpec&); \
  template void Solver<D>::constrain_sdf_walls(NodeField<Vec<D>>&, bool);

MPM_SDF_MEMBERS(1)
MPM_SDF_MEMBERS(2)
MPM_SDF_MEMBERS(3)

}  // namespace mpm
