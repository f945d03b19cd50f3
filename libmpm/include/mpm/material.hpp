#pragma once
// Constitutive models: a closed set held in a std::variant and dispatched once per material
// group with std::visit, never per particle.
//
// 1D is a bar in uniaxial stress (modulus E, wave speed sqrt(E/rho)); 2D is plane strain; 3D is
// the full model.

#include <algorithm>
#include <cmath>
#include <string_view>
#include <type_traits>
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

/// Drucker-Prager elastoplasticity for granular material (perfect plasticity, linear elastic
/// K and G, Jaumann-rotated rate form). Yield f = sqrt(J2) + alpha I1 - k, plastic potential
/// g = sqrt(J2) + alpha_psi I1 (non-associated when the dilatancy angle differs from the
/// friction angle), and a tension cut-off on the mean stress. alpha, k and alpha_psi are
/// matched to Mohr-Coulomb in plane strain: alpha = tan(phi) / sqrt(9 + 12 tan^2(phi)),
/// k = 3 c / sqrt(9 + 12 tan^2(phi)). Tension positive; I1 = tr(sigma).
struct DruckerPrager {
  double density = 0.0;
  double youngs_modulus = 0.0;
  double poisson_ratio = 0.0;
  double alpha = 0.0;           ///< from the friction angle
  double alpha_psi = 0.0;       ///< from the dilatancy angle
  double k = 0.0;               ///< from the cohesion (Pa)
  double tension_cutoff = 0.0;  ///< largest mean stress I1/3 (Pa, <= the apex k / (3 alpha))
  /// mu(I) rheology (Jop, Forterre & Pouliquen 2006; scene model "mu_i") when grain_diameter > 0:
  /// the cone is sqrt(J2) = mu(I) P (alpha = mu(I) / 3, no cohesion, no dilatancy, tension
  /// cut-off at the apex P = 0), mu(I) = mu_s + (mu_2 - mu_s) / (1 + I_0 / I), with the
  /// inertial number I = gamma_dot d / sqrt(P / rho_s) of the step: gamma_dot =
  /// sqrt(2 dev(D):dev(D)), P = -I1 / 3 of the trial stress (which the return does not change).
  double mu_s = 0.0;
  double mu_2 = 0.0;
  double inertial_i0 = 0.0;     ///< I_0
  double grain_diameter = 0.0;  ///< d (m); 0: rate-independent Drucker-Prager
  double grain_density = 0.0;   ///< rho_s (kg/m^3)
};

/// mu(I) of the rheology above, for a shear rate gamma_dot (1/s) and a pressure P (Pa, > 0).
inline double inertial_friction(const DruckerPrager& m, double gamma_dot, double pressure) {
  if (!(pressure > 0.0) || !(gamma_dot > 0.0)) return m.mu_s;
  const double I = gamma_dot * m.grain_diameter / std::sqrt(pressure / m.grain_density);
  return m.mu_s + (m.mu_2 - m.mu_s) * I / (I + m.inertial_i0);
}

/// Weakly compressible Newtonian fluid: Tait pressure p = B ((1/J)^gamma - 1), B = rho c0^2 /
/// gamma, no tension (a liquid cavitates rather than pull: p >= 0), and viscous stress
/// 2 mu dev(D).
struct NewtonianFluid {
  double density = 0.0;
  double speed_of_sound = 0.0;  ///< c0 (m/s): pick >= 10 times the fastest flow speed
  double gamma = 7.0;
  double viscosity = 0.0;  ///< dynamic viscosity mu (Pa s)
};

/// Bingham viscoplastic debris (Papanastasiou regularisation): the Tait pressure of
/// NewtonianFluid and deviatoric stress 2 mu_app dev(D) with
/// mu_app = eta_p + tau_y (1 - exp(-m gamma_dot)) / gamma_dot, gamma_dot = sqrt(2 dev(D):dev(D)),
/// so that in simple shear tau = eta_p gamma_dot + tau_y (1 - exp(-m gamma_dot)).
struct Bingham {
  double density = 0.0;
  double speed_of_sound = 0.0;
  double gamma = 7.0;
  double yield_stress = 0.0;       ///< tau_y (Pa)
  double plastic_viscosity = 0.0;  ///< eta_p (Pa s)
  double regularization = 0.0;     ///< m (s); mu_app never exceeds eta_p + tau_y m
};

using Material = std::variant<LinearElastic, NeoHookean, DruckerPrager, NewtonianFluid, Bingham>;

std::string_view model_name(const Material& m);

/// Per-particle state beyond F and sigma: the out-of-plane stress of plane strain (2D
/// plasticity needs the full 3D stress) and the accumulated equivalent plastic strain.
struct PointState {
  double stress_zz = 0.0;
  double plastic_strain = 0.0;
};

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

template <class M>
concept Fluid = std::is_same_v<M, NewtonianFluid> || std::is_same_v<M, Bingham>;

/// Longitudinal wave speed at the reference state, for the CFL condition.
template <int D>
double wave_speed(const Material& material) {
  return std::visit(
      [](const auto& m) {
        using M = std::decay_t<decltype(m)>;
        if constexpr (Fluid<M>) {
          return m.speed_of_sound;
        } else {
          return std::sqrt(p_wave_modulus<D>(m.youngs_modulus, m.poisson_ratio) / m.density);
        }
      },
      material);
}

/// Largest viscosity the material can show (Pa s; 0 for solids): it limits the explicit step to
/// rho h^2 / (2 D mu).
inline double max_viscosity(const Material& material) {
  return std::visit(
      [](const auto& m) {
        using M = std::decay_t<decltype(m)>;
        if constexpr (std::is_same_v<M, NewtonianFluid>) {
          return m.viscosity;
        } else if constexpr (std::is_same_v<M, Bingham>) {
          return m.plastic_viscosity + m.yield_stress * m.regularization;
        } else {
          return 0.0;
        }
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

/// The full 3D stress of a D-dimensional one whose out-of-plane normal stresses are stress_zz
/// (plane strain: the zz entry).
template <int D>
Eigen::Matrix3d stress_3d(const Mat<D>& sigma, double stress_zz) {
  Eigen::Matrix3d s3 = Eigen::Matrix3d::Zero();
  s3.topLeftCorner<D, D>() = sigma;
  for (int d = D; d < 3; ++d) s3(d, d) = stress_zz;
  return s3;
}

/// The largest volume ratio J = det F of a particle that has come apart: a Drucker-Prager
/// particle being pulled apart (its trial mean stress past the tension cut-off) or a fluid one
/// (pressure-free above J = 1). It carries no pressure, and the volume it claims beyond a loose
/// packing means nothing physical; but it weights the particle's stress once it is compressed or
/// sheared again (the force is V sigma grad N). A lone particle thrown off a debris flow's edge
/// kept stretching to J ~ 48,000 (750 m^3 for a 0.016 m^3 particle), then landed at 24 m/s and
/// the stress of that volume inverted it (docs/debris.md). A particle in contact is far from it
/// (a granular mass that keeps its grains touching dilates by tens of percent): only spray is
/// capped.
inline constexpr double kSeparatedMaxDilation = 2.0;

/// Scales F isotropically (its shape kept) so that det F <= kSeparatedMaxDilation; returns
/// det F after.
template <int D>
double cap_separated_dilation(Mat<D>& F) {
  const double J = F.determinant();
  if (!(J > kSeparatedMaxDilation)) return J;
  F *= std::pow(kSeparatedMaxDilation / J, 1.0 / D);
  return kSeparatedMaxDilation;
}

/// Drucker-Prager: Jaumann-rotate sigma with the spin of L, add the elastic trial increment and
/// return to the cone, its apex or the tension cut-off. For linear elasticity and a linear
/// potential the single-step return is exact (no iteration): on the cone
/// dlambda = f_trial / (G + 9 K alpha alpha_psi). In 2D (plane strain) the out-of-plane stress
/// is carried in state.stress_zz. (1D would be uniaxial strain with the lateral stresses in
/// stress_zz; scenes reject these models in 1D, whose elastic bar is in uniaxial stress.)
template <int D>
void update_stress(const DruckerPrager& m, const Mat<D>& L, double dt, Mat<D>& F, Mat<D>& sigma,
                   PointState& state) {
  F = (Mat<D>::Identity() + dt * L) * F;
  const Lame l = lame(m.youngs_modulus, m.poisson_ratio);
  const double G = l.mu, K = l.lambda + 2.0 / 3.0 * l.mu;
  const Mat<D> Dv = 0.5 * (L + L.transpose());
  const Mat<D> W = 0.5 * (L - L.transpose());
  Eigen::Matrix3d s3 = stress_3d<D>(sigma + dt * (W * sigma - sigma * W), state.stress_zz);
  Eigen::Matrix3d d3 = Eigen::Matrix3d::Zero();
  d3.topLeftCorner<D, D>() = dt * Dv;
  // Elastic trial.
  s3 += l.lambda * d3.trace() * Eigen::Matrix3d::Identity() + 2.0 * l.mu * d3;
  const double I1 = s3.trace();
  if (I1 > 3.0 * m.tension_cutoff) cap_separated_dilation<D>(F);  // being pulled apart
  const Eigen::Matrix3d dev = s3 - I1 / 3.0 * Eigen::Matrix3d::Identity();
  const double q = std::sqrt(0.5 * (dev.array() * dev.array()).sum());  // sqrt(J2)
  double alpha = m.alpha;
  if (m.grain_diameter > 0.0 && dt > 0.0) {
    const Eigen::Matrix3d rate = (d3 - d3.trace() / 3.0 * Eigen::Matrix3d::Identity()) / dt;
    alpha =
        inertial_friction(m, std::sqrt(2.0 * (rate.array() * rate.array()).sum()), -I1 / 3.0) / 3.0;
  }
  double I1_new = I1;
  double q_new = q;
  double dlambda = 0.0;
  const double f = q + alpha * I1 - m.k;
  if (f > 0.0) {
    dlambda = f / (G + 9.0 * K * alpha * m.alpha_psi);
    q_new = q - G * dlambda;
    I1_new = I1 - 9.0 * K * m.alpha_psi * dlambda;
    if (q_new < 0.0) {
      // Past the apex: the deviator is gone and the mean stress sits at the apex.
      q_new = 0.0;
      I1_new = alpha > 0.0 ? m.k / alpha : I1;
      dlambda = q / G;
    }
  }
  // Tension cut-off on the mean stress; the deviator then fits the cone at that pressure.
  if (I1_new > 3.0 * m.tension_cutoff) {
    I1_new = 3.0 * m.tension_cutoff;
    q_new = std::min(q_new, std::max(0.0, m.k - alpha * I1_new));
  }
  state.plastic_strain += dlambda;
  const Eigen::Matrix3d out =
      (q > 0.0 ? q_new / q : 0.0) * dev + I1_new / 3.0 * Eigen::Matrix3d::Identity();
  sigma = out.topLeftCorner<D, D>();
  if constexpr (D < 3) state.stress_zz = out(2, 2);
}

/// Tait modulus B = rho c0^2 / gamma of a fluid.
template <Fluid M>
double tait_modulus(const M& m) {
  return m.density * m.speed_of_sound * m.speed_of_sound / m.gamma;
}

/// Tait pressure (no tension) from J = V / V0.
template <Fluid M>
double tait_pressure(const M& m, double J) {
  return std::max(0.0, tait_modulus(m) * (std::pow(J, -m.gamma) - 1.0));
}

/// Newtonian fluid and Bingham: sigma = -p(J) I + 2 mu_app dev(D), D = sym(L) at the step.
template <int D, Fluid M>
void update_stress(const M& m, const Mat<D>& L, double dt, Mat<D>& F, Mat<D>& sigma,
                   PointState& /*state*/) {
  F = (Mat<D>::Identity() + dt * L) * F;
  const double J = cap_separated_dilation<D>(F);  // spray: see kSeparatedMaxDilation
  // The deviator of the rate of deformation in 3D terms (the missing directions have D = 0).
  const Mat<D> Dv = 0.5 * (L + L.transpose());
  const double third_trace = Dv.trace() / 3.0;
  const Mat<D> dev = Dv - third_trace * Mat<D>::Identity();
  const double dev_norm2 = (dev.array() * dev.array()).sum() + (3 - D) * third_trace * third_trace;
  double mu = 0.0;
  if constexpr (std::is_same_v<M, NewtonianFluid>) {
    mu = m.viscosity;
  } else {
    const double rate = std::sqrt(2.0 * dev_norm2);
    // (1 - exp(-m x)) / x -> m as x -> 0: expm1 keeps it accurate at small rates.
    const double yield_part = rate > 1e-12 / m.regularization
                                  ? -std::expm1(-m.regularization * rate) / rate
                                  : m.regularization;
    mu = m.plastic_viscosity + m.yield_stress * yield_part;
  }
  sigma = -tait_pressure(m, J) * Mat<D>::Identity() + 2.0 * mu * dev;
}

/// The models without extra state take the same call.
template <int D, class M>
requires std::is_same_v<M, LinearElastic> || std::is_same_v<M, NeoHookean>
void update_stress(const M& m, const Mat<D>& L, double dt, Mat<D>& F, Mat<D>& sigma,
                   PointState& /*state*/) {
  update_stress<D>(m, L, dt, F, sigma);
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

/// Drucker-Prager: the elastic energy of the current stress (linear K, G; plane strain counts
/// the out-of-plane stress).
template <int D>
double strain_energy(const DruckerPrager& m, const Mat<D>& F, const Mat<D>& sigma, double volume0,
                     double stress_zz) {
  const Eigen::Matrix3d s3 = stress_3d<D>(sigma, stress_zz);
  const Lame l = lame(m.youngs_modulus, m.poisson_ratio);
  const double K = l.lambda + 2.0 / 3.0 * l.mu;
  const double I1 = s3.trace();
  const Eigen::Matrix3d dev = s3 - I1 / 3.0 * Eigen::Matrix3d::Identity();
  return (I1 * I1 / (18.0 * K) + (dev.array() * dev.array()).sum() / (4.0 * l.mu)) *
         F.determinant() * volume0;
}

/// Fluids: the work stored by the Tait pressure, -V0 int_1^J p(J') dJ' (zero once expanded).
template <int D, Fluid M>
double strain_energy(const M& m, const Mat<D>& F, const Mat<D>& /*sigma*/, double volume0,
                     double /*stress_zz*/) {
  const double J = std::min(F.determinant(), 1.0);
  return tait_modulus(m) * volume0 *
         ((std::pow(J, 1.0 - m.gamma) - 1.0) / (m.gamma - 1.0) + (J - 1.0));
}

template <int D, class M>
requires std::is_same_v<M, LinearElastic> || std::is_same_v<M, NeoHookean>
double strain_energy(const M& m, const Mat<D>& F, const Mat<D>& sigma, double volume0,
                     double /*stress_zz*/) {
  return strain_energy<D>(m, F, sigma, volume0);
}

}  // namespace mpm
