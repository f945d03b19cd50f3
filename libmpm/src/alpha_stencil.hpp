#pragma once
// The boundary-grid basis of one particle, shared by the Blending and Enhanced steps.

#include <array>

#include "mpm/dual_grid.hpp"
#include "mpmgeom/boundary_grid.hpp"
#include "mpmgeom/locator.hpp"

namespace mpm {

template <int D>
AlphaStencil<D> alpha_stencil(const DualWall<D>& w, const mpmgeom::LayerLocator::Location& at) {
  const mpmgeom::AlphaBasis b = mpmgeom::alpha_basis(D, at.xi);
  AlphaStencil<D> s;
  s.count = DualWall<D>::kCellNodes;
  const auto& nodes = w.cell_nodes[static_cast<std::size_t>(at.cell)];
  for (int k = 0; k < s.count; ++k) {
    s.node[k] = nodes[static_cast<std::size_t>(k)];
    s.N[k] = b.N[k];
  }
  // dx/dxi as the locator's Newton formed it at xi (the cell's nodes are not read again).
  const Mat<D> inv_jt = at.jacobian.template topLeftCorner<D, D>().inverse().transpose();
  for (int k = 0; k < s.count; ++k) {
    s.dN[k] = inv_jt * b.dN.row(k).template head<D>().transpose();
  }
  return s;
}

}  // namespace mpm
