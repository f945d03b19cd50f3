#pragma once
// Constitutive models: a closed set held in a std::variant and dispatched once per material
// group with std::visit, never per particle.
//
// 1D is a bar in uniaxial stress (modulus E, wave speed sqrt(E/rho)); 2D is plane strain; 3D is
// the full model.

#include <cmath>
#include <string_view>
#include <variant>

#include "mpm/types.hpp"

namespace mpm {

/// Small-strain isotropic elasticity in rate form: sigma += C : sym(L) dt.
struct LinearElastic {
  double density = 0.0;
  double youngs_modulus = 0.0;
  double poisson_ratio = 0.0;
};

/// Compressible Neo-Hookean: sigma = mu/J (F F^T - I) + lambda ln(J)/J I.
struct NeoHookean {
  double density = 0.0;
  double youngs_modulus = 0.0;
  double poisson_ratio = 0.0;
};

using Material = std::variant<LinearElastic, NeoHookean>;

std::string_view model_name(const Material& m);

struct Lame {
  double lambda;
  double mu;
};

inline Lame lame(double youngs_modulus, double poisson_ratio) {
  const double nu = poisson_ratio;
  return {youngs_modulus * nu / ((1.0 + nu) * (1.0 - 2.0 * nu)),
          youngs_modulus / (2.0 * (1.0 + nu))};
}

/// Small-strain P-wave modulus of the D-dimensional model: E for the 1D bar, lambda + 2 mu for
/// plane strain and 3D.
template <int D>
double p_wave_modulus(double youngs_modulus, double poisson_ratio) {
  if constexpr (D == 1) {
    return youngs_modulus;
  } else {
    const Lame l = lame(youngs_modulus, poisson_ratio);
    return l.lambda + 2.0 * l.mu;
  }
}

/// Longitudinal wave speed at the reference state, for the CFL condition.
template <int D>
double wave_speed(const Material& material) {
  return std::visit(
      [](const auto& m) {
        return std::sqrt(p_wave_modulus<D>(m.youngs_modulus, m.poisson_ratio) / m.density);
      },
      material);
}

inline double density(const Material& material) {
  return std::visit([](const auto& m) { return m.density; }, material);
}

/// Advances F and sigma over dt given the velocity gradient L (evaluated at the start of the step).
template <int D>
void update_stress(const LinearElastic& m, const Mat<D>& L, double dt, Mat<D>& F, Mat<D>& sigma) {
  F = (Mat<D>::Identity() + dt * L) * F;
  const Mat<D> strain_increment = 0.5 * dt * (L + L.transpose());
  if constexpr (D == 1) {
    sigma += m.youngs_modulus * strain_increment;
  } else {
    const Lame l = lame(m.youngs_modulus, m.poisson_ratio);
    sigma +=
        l.lambda * strain_increment.trace() * Mat<D>::Identity() + 2.0 * l.mu * strain_increment;
  }
}

template <int D>
void update_stress(const NeoHookean& m, const Mat<D>& L, double dt, Mat<D>& F, Mat<D>& sigma) {
  F = (Mat<D>::Identity() + dt * L) * F;
  const double J = F.determinant();
  if constexpr (D == 1) {
    // 1D hyperelastic bar with psi = E/2 ((J^2 - 1)/2 - ln J): tangent E at J = 1.
    sigma(0, 0) = 0.5 * m.youngs_modulus * (J - 1.0 / J);
  } else {
    const Lame l = lame(m.youngs_modulus, m.poisson_ratio);
    sigma = (l.mu / J) * (F * F.transpose() - Mat<D>::Identity()) +
            (l.lambda * std::log(J) / J) * Mat<D>::Identity();
  }
}

/// Stored elastic energy of one particle (J).
template <int D>
double strain_energy(const LinearElastic& m, const Mat<D>& F, const Mat<D>& sigma, double volume0) {
  const double volume = F.determinant() * volume0;
  if constexpr (D == 1) {
    return 0.5 * sigma(0, 0) * sigma(0, 0) / m.youngs_modulus * volume;
  } else {
    // Invert sigma = lambda tr(eps) I + 2 mu eps in D dimensions: tr(sigma) = (D lambda + 2 mu)
    // tr(eps).
    const Lame l = lame(m.youngs_modulus, m.poisson_ratio);
    const Mat<D> strain =
        (sigma - l.lambda * sigma.trace() / (D * l.lambda + 2.0 * l.mu) * Mat<D>::Identity()) /
        (2.0 * l.mu);
    return 0.5 * (sigma.array() * strain.array()).sum() * volume;
  }
}

template <int D>
double strain_energy(const NeoHookean& m, const Mat<D>& F, const Mat<D>& /*sigma*/,
                     double volume0) {
  const double J = F.determinant();
  const double log_j = std::log(J);
  if constexpr (D == 1) {
    return 0.5 * m.youngs_modulus * (0.5 * (J * J - 1.0) - log_j) * volume0;
  } else {
    const Lame l = lame(m.youngs_modulus, m.poisson_ratio);
    return (0.5 * l.mu * ((F.transpose() * F).trace() - D) - l.mu * log_j +
            0.5 * l.lambda * log_j * log_j) *
           volume0;
  }
}

}  // namespace mpm
