#pragma once
// Small fixed-size Eigen types shared by the solver. D is the spatial dimension (1, 2 or 3).

#include <Eigen/Core>
#include <Eigen/LU>  // determinant

namespace mpm {

template <int D>
using Vec = Eigen::Matrix<double, D, 1>;
template <int D>
using Mat = Eigen::Matrix<double, D, D>;
template <int D>
using Index = Eigen::Matrix<int, D, 1>;

/// Pads a D-vector to 3 components (output, XDMF).
template <int D>
Eigen::Vector3d pad3(const Vec<D>& v) {
  Eigen::Vector3d out = Eigen::Vector3d::Zero();
  out.template head<D>() = v;
  return out;
}

}  // namespace mpm
