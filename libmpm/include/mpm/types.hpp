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

/// The multi-index of entry `at` of a lattice with `size` points per axis, last axis fastest.
template <int D>
Index<D> lattice_index(long at, const Index<D>& size) {
  Index<D> i;
  for (int d = D - 1; d >= 0; --d) {
    i[d] = static_cast<int>(at % size[d]);
    at /= size[d];
  }
  return i;
}

/// The entry of multi-index i in a lattice with `size` points per axis, last axis fastest
/// (lattice_index()'s inverse).
template <int D>
long lattice_offset(const Index<D>& i, const Index<D>& size) {
  long at = 0;
  for (int d = 0; d < D; ++d) at = at * size[d] + i[d];
  return at;
}

/// f(i) for every multi-index i with lo <= i <= hi (each axis, inclusive), last axis fastest;
/// nothing if the box is empty along an axis.
template <int D, class F>
void for_each_in_box(const Index<D>& lo, const Index<D>& hi, F&& f) {
  if ((lo.array() > hi.array()).any()) return;
  Index<D> i = lo;
  while (true) {
    f(static_cast<const Index<D>&>(i));
    int d = D - 1;
    while (d >= 0 && i[d] == hi[d]) {
      i[d] = lo[d];
      --d;
    }
    if (d < 0) return;
    ++i[d];
  }
}

/// Pads a D-vector to 3 components (output, XDMF).
template <int D>
Eigen::Vector3d pad3(const Vec<D>& v) {
  Eigen::Vector3d out = Eigen::Vector3d::Zero();
  out.template head<D>() = v;
  return out;
}

}  // namespace mpm
