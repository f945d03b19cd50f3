#pragma once
// Wall conditions: a closed set applied to grid-node velocities in the wall's own frame
// (normal n pointing from the wall into the material).

#include <Eigen/Cholesky>
#include <Eigen/QR>
#include <algorithm>
#include <bit>
#include <cmath>
#include <string>
#include <variant>

#include "mpm/types.hpp"

namespace mpm {

struct Sticky {};  ///< no relative motion while in contact
struct Slip {};    ///< frictionless: only the normal component is removed
struct Friction {  ///< Coulomb friction with coefficient mu
  double mu = 0.0;
};
using WallCondition = std::variant<Sticky, Slip, Friction>;

struct WallContact {
  WallCondition condition;
  /// true: unilateral contact, material moving away from the wall is left free (a block can
  /// bounce off, a bar can rebound). false: the wall holds the material (bonded).
  bool separable = false;
  /// Separable dual-grid walls: a Gamma node acts only where a particle lying over its share of
  /// the wall facet has its edge within this many particle half-sizes of the wall along the
  /// node's normal (the particle touches the wall there), not wherever the node's support
  /// reaches the material. The default is a guard against round-off.
  double touch_tolerance = 0.01;
};

/// A wall on one face of the grid box. In 1D only x faces exist, in 2D x and y.
struct BoxWall {
  std::string name;  ///< "xmin", "xmax", "ymin", ...
  int axis = 0;
  int side = -1;  ///< -1: at the box minimum (normal +e_axis), +1: at the maximum
  WallContact contact;
};

/// The wall condition on a node in contact, given its velocity `slid` with the normal part taken
/// out (frictionless sliding) and the size of that normal change per unit mass: sticky stops it,
/// slip keeps it, Coulomb friction takes at most mu times the normal impulse from its speed.
template <int D, class Condition>
Vec<D> apply_condition(const Condition& condition, const Vec<D>& slid, double normal_change) {
  if constexpr (std::is_same_v<Condition, Sticky>) {
    return Vec<D>::Zero();
  } else if constexpr (std::is_same_v<Condition, Slip>) {
    return slid;
  } else {
    const double speed = slid.norm();
    if (speed <= 0.0) return slid;
    return slid * std::max(0.0, 1.0 - condition.mu * normal_change / speed);
  }
}

/// The velocity of a node in contact after the wall condition, given the unconstrained velocity
/// v (relative to the wall) and the unit normal n into the material.
template <int D, class Condition>
Vec<D> constrain_velocity(const Condition& condition, bool separable, const Vec<D>& n,
                          const Vec<D>& v) {
  const double vn = v.dot(n);
  if (separable && vn >= 0.0) return v;  // moving away: no contact force
  return apply_condition<D>(condition, Vec<D>(v - vn * n), std::abs(vn));
}

/// The most distinct facet normals a corner node is held against (constrain_velocity_in_corner).
constexpr int kMaxCornerNormals = 8;

/// The velocity nearest to v (Euclidean: a node has one mass) that enters none of the given
/// planes: n_i . u >= 0 for each unit normal n_i of the wall facets meeting at a concave corner
/// or crease. The projection onto that polyhedral cone is the u = v + sum_A l_i n_i with
/// l_i >= 0 and n_i . u = 0 on an active set A that leaves every other n_j . u >= 0; at most D
/// planes are active, and the count is small (the facets' distinct normals), so the active sets
/// are tried smallest first. Zero (the corner itself) if none fits, as where the normals span
/// no cone with an interior. lambda (count entries, if given) receives each l_i (0 off A).
template <int D>
requires(D > 1) Vec<D> project_to_cone(const Vec<D>* n, int count, const Vec<D>& v,
                                       double* lambda = nullptr) {
  if (lambda) std::fill(lambda, lambda + count, 0.0);
  const double tol = 1e-12 * v.norm();
  const auto feasible = [&](const Vec<D>& u) {
    for (int j = 0; j < count; ++j) {
      if (n[j].dot(u) < -tol) return false;
    }
    return true;
  };
  if (feasible(v)) return v;
  const unsigned subsets = 1u << count;
  for (int size = 1; size <= std::min(D, count); ++size) {
    for (unsigned mask = 1; mask < subsets; ++mask) {
      if (std::popcount(mask) != size) continue;
      Eigen::Matrix<double, D, Eigen::Dynamic, 0, D, D> active(D, size);
      int k = 0;
      for (int i = 0; i < count; ++i) {
        if (mask & (1u << i)) active.col(k++) = n[i];
      }
      const Eigen::Matrix<double, Eigen::Dynamic, Eigen::Dynamic, 0, D, D> gram =
          active.transpose() * active;
      const Eigen::LDLT<Eigen::Matrix<double, Eigen::Dynamic, Eigen::Dynamic, 0, D, D>> ldlt(gram);
      // Dependent normals: a smaller active set spans the same planes.
      if (ldlt.info() != Eigen::Success || ldlt.vectorD().minCoeff() <= 1e-12) continue;
      const Eigen::Matrix<double, Eigen::Dynamic, 1, 0, D, 1> l =
          ldlt.solve(-(active.transpose() * v));
      if (l.minCoeff() < 0.0) continue;
      const Vec<D> u = v + active * l;
      if (!feasible(u)) continue;
      if (lambda) {
        k = 0;
        for (int i = 0; i < count; ++i) {
          if (mask & (1u << i)) lambda[i] = l[k++];
        }
      }
      return u;
    }
  }
  return Vec<D>::Zero();
}

/// The velocity a node at a concave corner or crease may keep before friction, with the facets'
/// distinct unit normals n[0 .. count), count <= kMaxCornerNormals: separable, the nearest
/// velocity entering no facet (v itself if it enters none); bonded, the part of v along no
/// facet's normal (the node slides only along every facet at once). lambda (count entries, if
/// given) receives the normal change of velocity each facet makes, l_i along n_i.
template <int D>
requires(D > 1) Vec<D> corner_slide(bool separable, const Vec<D>* n, int count, const Vec<D>& v,
                                    double* lambda) {
  if (separable) return project_to_cone<D>(n, count, v, lambda);
  // The part of v in no facet's normal direction (orthogonal to their span).
  Eigen::Matrix<double, D, Eigen::Dynamic, 0, D, kMaxCornerNormals> normals(D, count);
  for (int i = 0; i < count; ++i) normals.col(i) = n[i];
  const Eigen::ColPivHouseholderQR<decltype(normals)> qr(normals);
  const auto q = qr.householderQ() * Mat<D>::Identity();
  Vec<D> u = v;
  for (Eigen::Index r = 0; r < qr.rank(); ++r) u -= q.col(r).dot(v) * q.col(r);
  if (lambda) {
    const Eigen::Matrix<double, Eigen::Dynamic, 1, 0, kMaxCornerNormals, 1> l = qr.solve(u - v);
    std::copy(l.data(), l.data() + count, lambda);
  }
  return u;
}

/// constrain_velocity() at a node where wall facets meet at a concave corner or crease, with
/// the facets' distinct unit normals n[0 .. count), count <= kMaxCornerNormals: the node may move
/// along none of them into the wall. Separable: free while v enters none; otherwise v is projected
/// onto the cone of velocities that enter none (slip), with Coulomb friction taking at most mu
/// times that projection's impulse from the sliding speed, or stopped (sticky). Bonded: the node
/// slides only along every facet at once (in 2D, and in 3D where three facets meet, it is held).
/// With one normal this is constrain_velocity(). lambda (count entries, if given) receives the
/// normal change of velocity each facet makes, l_i along n_i (the change less their sum is
/// friction's), so that a force can be shared among the facets' parts.
template <int D, class Condition>
requires(D > 1) Vec<D> constrain_velocity_in_corner(const Condition& condition, bool separable,
                                                    const Vec<D>* n, int count, const Vec<D>& v,
                                                    double* lambda = nullptr) {
  const Vec<D> u = corner_slide<D>(separable, n, count, v, lambda);
  if (separable && u == v) return v;  // enters no facet: no contact force
  return apply_condition<D>(condition, u, (u - v).norm());
}

/// The condition at a corner whose facets belong to parts with conditions of their own (a
/// barrier's foot on the terrain, each with its friction), given each facet's normal push
/// lambda[i]: sticky if a facet that pushes is sticky (its material does not slide along it, and
/// the corner's only free direction runs along it); otherwise Coulomb friction whose coefficient
/// is the facets' own (slip: 0) weighted by their pushes |lambda_i|, so that a facet the node
/// does not press on adds no friction, and equal coefficients give that coefficient back. No
/// facet pushing (the node already slides along them all): the first facet's condition, which
/// then has nothing to act on.
inline WallCondition corner_condition(const WallCondition* const* conditions, const double* lambda,
                                      int count) {
  double pushes = 0.0, weighted = 0.0;
  bool any_friction = false;
  for (int i = 0; i < count; ++i) {
    const double push = std::abs(lambda[i]);
    if (push == 0.0) continue;
    if (std::holds_alternative<Sticky>(*conditions[i])) return Sticky{};
    pushes += push;
    if (const auto* f = std::get_if<Friction>(conditions[i])) {
      weighted += f->mu * push;
      any_friction = true;
    }
  }
  if (pushes == 0.0) return *conditions[0];
  if (!any_friction) return Slip{};
  return Friction{weighted / pushes};
}

/// constrain_velocity_in_corner() where each facet has its own part's condition (conditions[i]
/// for n[i]), combined by corner_condition() from the facets' pushes. lambda as there (required).
template <int D>
requires(D > 1) Vec<D> constrain_velocity_in_corner_of_parts(const WallCondition* const* conditions,
                                                             bool separable, const Vec<D>* n,
                                                             int count, const Vec<D>& v,
                                                             double* lambda) {
  const Vec<D> u = corner_slide<D>(separable, n, count, v, lambda);
  if (separable && u == v) return v;  // enters no facet: no contact force
  return std::visit(
      [&](const auto& condition) { return apply_condition<D>(condition, u, (u - v).norm()); },
      corner_condition(conditions, lambda, count));
}

}  // namespace mpm
