#pragma once
// Wall conditions: a closed set applied to grid-node velocities in the wall's own frame
// (normal n pointing from the wall into the material).

#include <algorithm>
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

/// The velocity of a node in contact after the wall condition, given the unconstrained velocity
/// v (relative to the wall) and the unit normal n into the material.
template <int D, class Condition>
Vec<D> constrain_velocity(const Condition& condition, bool separable, const Vec<D>& n,
                          const Vec<D>& v) {
  const double vn = v.dot(n);
  if (separable && vn >= 0.0) return v;  // moving away: no contact force
  if constexpr (std::is_same_v<Condition, Sticky>) {
    return Vec<D>::Zero();
  } else {
    const Vec<D> vt = v - vn * n;
    if constexpr (std::is_same_v<Condition, Slip>) {
      return vt;
    } else {
      // Coulomb: the tangential impulse is at most mu times the normal impulse m |vn|.
      const double speed = vt.norm();
      if (speed <= 0.0) return vt;
      return vt * std::max(0.0, 1.0 - condition.mu * std::abs(vn) / speed);
    }
  }
}

}  // namespace mpm
