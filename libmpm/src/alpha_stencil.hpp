#pragma once
// The boundary-grid basis of one particle, shared by the Blending and Enhanced steps.

#include "mpm/dual_grid.hpp"
#include "mpmgeom/boundary_grid.hpp"

namespace mpm {

template <int D>
AlphaStencil<D> alpha_stencil(const DualWall<D>& w, int cell, const Eigen::Vector3d& xi) {
  const mpmgeom::AlphaBasis b = mpmgeom::alpha_basis(D, xi);
  AlphaStencil<D> s;
  s.count = w.layer->nodes_per_cell();
  Mat<D> J = Mat<D>::Zero();  // dx/dxi
  for (int k = 0; k < s.count; ++k) {
    s.node[k] = w.layer->cells(cell, k);
    s.N[k] = b.N[k];
    J += w.position[s.node[k]] * b.dN.row(k).template head<D>();
  }
  const Mat<D> inv_jt = J.inverse().transpose();
  for (int k = 0; k < s.count; ++k) {
    s.dN[k] = inv_jt * b.dN.row(k).template head<D>().transpose();
  }
  return s;
}

}  // namespace mpm
