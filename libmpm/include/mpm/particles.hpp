#pragma once
// Material points as a structure of arrays. Particles are stored grouped by material so that
// the constitutive update is dispatched once per group (see material.hpp).

#include <cstddef>
#include <vector>

#include "mpm/material.hpp"
#include "mpm/types.hpp"

namespace mpm {

template <int D>
struct Particles {
  std::vector<Vec<D>> position;
  std::vector<Vec<D>> velocity;
  std::vector<Mat<D>> affine;  ///< APIC velocity matrix C_p (zero for PIC/FLIP)
  std::vector<Mat<D>> deformation_gradient;
  std::vector<Mat<D>> stress;     ///< Cauchy stress
  std::vector<PointState> state;  ///< out-of-plane stress, plastic strain (material.hpp)
  std::vector<double> mass;
  std::vector<double> volume0;     ///< initial volume; current volume = det(F) * volume0
  std::vector<double> half_width;  ///< uGIMP half particle size in grid units (fixed)
  std::vector<int> material;
  std::vector<int> body;

  // Dual-grid ownership (Blending): the wall whose layer holds the particle (-1: the standard
  // grid owns it) and, this step, its place in the solver's list of layer particles (which
  // holds the layer cell and the natural coordinates in it).
  std::vector<int> layer_wall;
  std::vector<int> layer_slot;

  /// The step's displacement, dt times the gathered velocity: kept only where the particle
  /// velocity is not that velocity (FLIP); sized by the solver, empty otherwise.
  std::vector<Vec<D>> displacement;

  [[nodiscard]] std::size_t size() const { return position.size(); }

  void resize(std::size_t n) {
    position.resize(n, Vec<D>::Zero());
    velocity.resize(n, Vec<D>::Zero());
    affine.resize(n, Mat<D>::Zero());
    deformation_gradient.resize(n, Mat<D>::Identity());
    stress.resize(n, Mat<D>::Zero());
    state.resize(n, PointState{});
    mass.resize(n, 0.0);
    volume0.resize(n, 0.0);
    half_width.resize(n, 0.0);
    material.resize(n, 0);
    body.resize(n, 0);
    layer_wall.resize(n, -1);
    layer_slot.resize(n, -1);
  }
};

}  // namespace mpm
