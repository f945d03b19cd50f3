// Single-point constitutive tests: each model driven along a strain-rate path and compared with
// the closed-form answer of that path.
#include <gtest/gtest.h>

#include <cmath>
#include <numbers>

#include "mpm/material.hpp"

namespace {

using namespace mpm;

constexpr double kDeg = std::numbers::pi / 180.0;

/// Drucker-Prager matched to Mohr-Coulomb in plane strain, as the scene reader builds it.
DruckerPrager drucker_prager(double phi_deg, double psi_deg, double cohesion) {
  const auto match = [](double a) { return std::sqrt(9.0 + 12.0 * std::tan(a) * std::tan(a)); };
  const double phi = phi_deg * kDeg, psi = psi_deg * kDeg;
  DruckerPrager m{2000.0,
                  1.0e7,
                  0.3,
                  std::tan(phi) / match(phi),
                  std::tan(psi) / match(psi),
                  3.0 * cohesion / match(phi),
                  0.0};
  m.tension_cutoff = m.k / (3.0 * m.alpha);
  return m;
}

struct PlaneStress3 {
  double I1, q;
};

PlaneStress3 invariants(const Mat<2>& sigma, double szz) {
  const Eigen::Matrix3d s = stress_3d<2>(sigma, szz);
  const double I1 = s.trace();
  const Eigen::Matrix3d dev = s - I1 / 3.0 * Eigen::Matrix3d::Identity();
  return {I1, std::sqrt(0.5 * (dev.array() * dev.array()).sum())};
}

// Confined pure shear (D_xy = rate, no volume change, no spin) from an isotropic pressure p0.
// Exact: elastic (q = 2 G eps) until q = k - alpha I1; then, with dlambda = 2 G deps /
// (G + 9 K alpha alpha_psi), q grows at 2 G H deps, H = 9 K alpha alpha_psi / (G + 9 K alpha
// alpha_psi), and I1 falls at -9 K alpha_psi dlambda (dilatancy against the confinement raises
// the pressure). Zero dilatancy: q stays at the yield value. The return is exact for this linear
// path whatever the step, so the match is to round-off.
void expect_confined_shear_path(double psi_deg, double cohesion) {
  const DruckerPrager m = drucker_prager(30.0, psi_deg, cohesion);
  const Lame l = lame(m.youngs_modulus, m.poisson_ratio);
  const double G = l.mu, K = l.lambda + 2.0 / 3.0 * l.mu;
  const double p0 = 50e3;
  Mat<2> sigma = -p0 * Mat<2>::Identity(), F = Mat<2>::Identity();
  PointState state{-p0, 0.0};
  const double rate = 1.0, dt = 2e-5;  // eps_xy grows by 2e-5 a step (elastic limit ~ 3e-3)
  Mat<2> L;
  L << 0.0, rate, rate, 0.0;
  const double I1_0 = -3.0 * p0;
  const double q_yield = m.k - m.alpha * I1_0;
  const double eps_yield = q_yield / (2.0 * G);
  const double c = 9.0 * K * m.alpha * m.alpha_psi;
  double worst = 0.0;
  for (int step = 1; step <= 600; ++step) {
    update_stress<2>(m, L, dt, F, sigma, state);
    const double eps = rate * dt * step;
    double q_exact = 2.0 * G * eps, I1_exact = I1_0;
    if (eps > eps_yield) {
      const double dlambda = 2.0 * G * (eps - eps_yield) / (G + c);
      I1_exact = I1_0 - 9.0 * K * m.alpha_psi * dlambda;
      q_exact = m.k - m.alpha * I1_exact;
    }
    const PlaneStress3 got = invariants(sigma, state.stress_zz);
    worst = std::max(
        {worst, std::abs(got.q - q_exact) / q_yield, std::abs(got.I1 - I1_exact) / std::abs(I1_0)});
    // On or inside the cone at every step.
    EXPECT_LE(got.q + m.alpha * got.I1 - m.k, 1e-9 * q_yield);
  }
  EXPECT_GT(rate * dt * 600, 3.0 * eps_yield);  // the path goes well into plastic flow
  EXPECT_LT(worst, 1e-10) << "psi " << psi_deg << " c " << cohesion;
  EXPECT_GT(state.plastic_strain, 0.0);
}

TEST(DruckerPrager, ConfinedShearPathNonDilatant) { expect_confined_shear_path(0.0, 0.0); }
TEST(DruckerPrager, ConfinedShearPathDilatant) { expect_confined_shear_path(10.0, 0.0); }
TEST(DruckerPrager, ConfinedShearPathAssociatedCohesive) { expect_confined_shear_path(30.0, 5e3); }

// Uniform extension of a cohesive soil: the mean stress reaches the apex I1 = k / alpha and
// stays there with no deviator; with a lower tension cut-off it stops at 3 sigma_t.
TEST(DruckerPrager, ExtensionEndsAtApexOrTensionCutoff) {
  for (const double cutoff_fraction : {1.0, 0.25}) {
    DruckerPrager m = drucker_prager(30.0, 5.0, 10e3);
    m.tension_cutoff *= cutoff_fraction;
    Mat<2> sigma = Mat<2>::Zero(), F = Mat<2>::Identity();
    PointState state;
    Mat<2> L;
    L << 1.0, 0.2, 0.2, 0.5;  // extension with some shear
    for (int step = 0; step < 400; ++step) update_stress<2>(m, L, 1e-5, F, sigma, state);
    const PlaneStress3 got = invariants(sigma, state.stress_zz);
    EXPECT_NEAR(got.I1, 3.0 * m.tension_cutoff, 1e-9 * m.k / m.alpha);
    if (cutoff_fraction == 1.0) {
      EXPECT_NEAR(got.q, 0.0, 1e-9 * m.k);
    } else {
      // Below the apex the deviator may sit anywhere up to the cone at that pressure.
      EXPECT_LE(got.q, m.k - m.alpha * got.I1 + 1e-9 * m.k);
    }
  }
}

// Spray: cohesionless sand pulled apart without end (a particle thrown off a flow) is
// stress-free, and its volume stops at kSeparatedMaxDilation instead of growing with the
// extension (e^3 = 20 here); compressed again, it carries stress at once, from that volume.
TEST(DruckerPrager, PulledApartVolumeStopsAtTheLoosestDilation) {
  DruckerPrager m = drucker_prager(30.0, 0.0, 0.0);
  Mat<3> sigma = Mat<3>::Zero(), F = Mat<3>::Identity();
  PointState state;
  Mat<3> L = Mat<3>::Identity();
  L(0, 1) = 0.3;  // with some shear and spin
  const double dt = 1e-3;
  for (int step = 0; step < 1000; ++step) {
    update_stress<3>(m, L, dt, F, sigma, state);
    EXPECT_LE(F.determinant(), kSeparatedMaxDilation * (1.0 + 1e-12));
    EXPECT_EQ(sigma.norm(), 0.0);
  }
  EXPECT_NEAR(F.determinant(), kSeparatedMaxDilation, 1e-12);  // reached and held
  // Compression: the volume falls by the step's strain, and the mean stress is the elastic one.
  const double J_before = F.determinant();
  update_stress<3>(m, -Mat<3>::Identity(), dt, F, sigma, state);
  EXPECT_NEAR(F.determinant(), J_before * std::pow(1.0 - dt, 3), 1e-12);
  const Lame l = lame(m.youngs_modulus, m.poisson_ratio);
  EXPECT_NEAR(sigma.trace() / 3.0, -(3.0 * l.lambda + 2.0 * l.mu) * dt, 1e-9 * l.lambda * dt);
}

// Cohesionless sand cannot carry tension: any extension leaves it stress-free (the apex is 0).
// mu(I) in steady simple shear (L_xy = gamma_dot, with spin) from an isotropic pressure P0:
// simple shear keeps the volume and the Jaumann rotation keeps the trace, and without dilatancy
// the return keeps I1, so P = P0 throughout; once yielding, the return puts the stress on the
// cone, sqrt(J2) = mu(I) P0 with I = gamma_dot d / sqrt(P0 / rho_s). Exact to round-off at
// every plastic step, for rates from the quasi-static (I = 5e-3: mu -> mu_s) through I_0 (mu
// halfway) to the collisional (I = 50: mu -> mu_2). Glass beads of Jop et al. (2006): mu_s =
// tan 20.9, mu_2 = tan 32.76, I_0 = 0.279, d = 0.5 mm, rho_s = 2500.
TEST(MuI, SteadySimpleShearFollowsTheInertialFriction) {
  DruckerPrager m{1500.0, 1.0e7, 0.3, 0.0, 0.0, 0.0, 0.0};
  m.mu_s = std::tan(20.9 * kDeg);
  m.mu_2 = std::tan(32.76 * kDeg);
  m.inertial_i0 = 0.279;
  m.grain_diameter = 5e-4;
  m.grain_density = 2500.0;
  m.alpha = m.mu_s / 3.0;
  const double p0 = 1e4;  // sqrt(P0 / rho_s) = 2 m/s: I = gamma_dot * 2.5e-4
  for (const double inertial : {5e-3, 0.279, 50.0}) {
    const double gamma_dot = inertial * 2.0 / m.grain_diameter;
    const double dt = 2e-5 / gamma_dot;  // 2e-5 of shear a step: the cone within 90 steps
    const double mu = m.mu_s + (m.mu_2 - m.mu_s) / (1.0 + m.inertial_i0 / inertial);
    Mat<2> sigma = -p0 * Mat<2>::Identity(), F = Mat<2>::Identity(), L;
    L << 0.0, gamma_dot, 0.0, 0.0;
    PointState state{-p0, 0.0};
    int plastic = 0;
    for (int step = 0; step < 600; ++step) {
      update_stress<2>(m, L, dt, F, sigma, state);
      const PlaneStress3 got = invariants(sigma, state.stress_zz);
      EXPECT_NEAR(got.I1, -3.0 * p0, 1e-12 * p0) << "I " << inertial << " step " << step;
      EXPECT_LE(got.q, mu * p0 * (1.0 + 1e-12)) << "I " << inertial << " step " << step;
      if (got.q >= mu * p0 * (1.0 - 1e-12)) ++plastic;
    }
    EXPECT_GT(plastic, 400) << "I " << inertial;  // the path reaches the cone and flows on it
    const PlaneStress3 end = invariants(sigma, state.stress_zz);
    EXPECT_NEAR(end.q / p0, mu, 1e-12) << "I " << inertial;
    EXPECT_GT(state.plastic_strain, 0.0);
  }
}

TEST(DruckerPrager, CohesionlessExtensionIsStressFree) {
  const DruckerPrager m = drucker_prager(35.0, 0.0, 0.0);
  Mat<2> sigma = -1e3 * Mat<2>::Identity(), F = Mat<2>::Identity();
  PointState state{-1e3, 0.0};
  Mat<2> L;
  L << 2.0, 0.0, 0.0, 1.0;
  for (int step = 0; step < 100; ++step) update_stress<2>(m, L, 1e-4, F, sigma, state);
  EXPECT_LT(sigma.norm(), 1e-9);
  EXPECT_NEAR(state.stress_zz, 0.0, 1e-9);
}

// Simple shear of a Newtonian fluid: sigma_xy = mu gamma_dot, no pressure without a volume change.
TEST(NewtonianFluid, SimpleShearViscosity) {
  const NewtonianFluid m{1000.0, 20.0, 7.0, 0.8};
  for (const double gamma_dot : {0.01, 1.0, 50.0}) {
    Mat<2> sigma = Mat<2>::Zero(), F = Mat<2>::Identity();
    PointState state;
    Mat<2> L;
    L << 0.0, gamma_dot, 0.0, 0.0;
    update_stress<2>(m, L, 1e-6, F, sigma, state);
    EXPECT_NEAR(sigma(0, 1), m.viscosity * gamma_dot, 1e-12 * m.viscosity * gamma_dot);
    EXPECT_NEAR(sigma(1, 0), sigma(0, 1), 1e-15);
    EXPECT_NEAR(sigma(0, 0), 0.0, 1e-9);
  }
}

// Tait pressure: p = B (J^-gamma - 1) in compression, none in expansion (no tension).
TEST(NewtonianFluid, TaitPressureAndNoTension) {
  const NewtonianFluid m{1000.0, 20.0, 7.0, 0.0};
  const double B = m.density * m.speed_of_sound * m.speed_of_sound / m.gamma;
  for (const double J : {0.98, 0.995, 1.01}) {
    Mat<3> sigma = Mat<3>::Zero();
    Mat<3> F = std::cbrt(J) * Mat<3>::Identity();
    PointState state;
    update_stress<3>(m, Mat<3>::Zero(), 1e-6, F, sigma, state);
    const double p = std::max(0.0, B * (std::pow(J, -m.gamma) - 1.0));
    EXPECT_NEAR(-sigma(0, 0), p, 1e-9 * B);
    EXPECT_NEAR(sigma(0, 1), 0.0, 1e-12);
  }
}

// Spray of a fluid: expanded without end it stays pressure-free and its volume stops at
// kSeparatedMaxDilation, with the shear stress of the rate it is given (Bingham and Newtonian).
TEST(Fluids, ExpandedVolumeStopsAtTheLoosestDilation) {
  const NewtonianFluid water{1000.0, 20.0, 7.0, 1e-3};
  const Bingham debris{2000.0, 30.0, 7.0, 500.0, 20.0, 200.0};
  auto expand = [](const auto& m) {
    Mat<3> sigma = Mat<3>::Zero(), F = Mat<3>::Identity(), L = Mat<3>::Identity();
    PointState state;
    for (int step = 0; step < 1000; ++step) {
      update_stress<3>(m, L, 1e-3, F, sigma, state);
      EXPECT_LE(F.determinant(), kSeparatedMaxDilation * (1.0 + 1e-12));
      EXPECT_NEAR(sigma.trace(), 0.0, 1e-9);  // no pressure, a traceless viscous stress
    }
    EXPECT_NEAR(F.determinant(), kSeparatedMaxDilation, 1e-12);
  };
  expand(water);
  expand(debris);
}

// Simple shear of Bingham debris: tau = eta_p gamma_dot + tau_y (1 - exp(-m gamma_dot)), which
// tends to the Bingham line tau_y + eta_p gamma_dot once m gamma_dot >> 1.
TEST(Bingham, SimpleShearFlowCurve) {
  const Bingham m{2000.0, 30.0, 7.0, 500.0, 20.0, 200.0};
  for (const double gamma_dot : {1e-4, 1e-2, 0.5, 10.0}) {
    for (const int dim : {2, 3}) {
      double tau = 0.0;
      if (dim == 2) {
        Mat<2> sigma = Mat<2>::Zero(), F = Mat<2>::Identity();
        PointState state;
        Mat<2> L;
        L << 0.0, gamma_dot, 0.0, 0.0;
        update_stress<2>(m, L, 1e-7, F, sigma, state);
        tau = sigma(0, 1);
      } else {
        Mat<3> sigma = Mat<3>::Zero(), F = Mat<3>::Identity();
        PointState state;
        Mat<3> L = Mat<3>::Zero();
        L(0, 2) = gamma_dot;
        update_stress<3>(m, L, 1e-7, F, sigma, state);
        tau = sigma(0, 2);
      }
      const double exact = m.plastic_viscosity * gamma_dot +
                           m.yield_stress * (1.0 - std::exp(-m.regularization * gamma_dot));
      EXPECT_NEAR(tau, exact, 1e-9 * exact) << "gamma_dot " << gamma_dot << " dim " << dim;
    }
  }
}

}  // namespace
