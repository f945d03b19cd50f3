#pragma once
// Number formatting for the one-line messages of libgeom (internal).

#include <sstream>
#include <string>

#include <Eigen/Core>

namespace mpmgeom::detail {

inline std::string format_number(double x) {
  std::ostringstream out;
  out << x;
  return out.str();
}

inline std::string format_point(const Eigen::Vector3d& p) {
  return '(' + format_number(p.x()) + ", " + format_number(p.y()) + ", " + format_number(p.z()) +
         ')';
}

}  // namespace mpmgeom::detail
