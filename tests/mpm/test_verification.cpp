// Verification against exact answers (DESIGN.md section 5) on the shipped scenes.

#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <functional>
#include <numbers>

#include <nlohmann/json.hpp>

#include "mpm/solver.hpp"
#include "support/run_until.hpp"
#include "support/scenes.hpp"

namespace mpm {
namespace {

using mpm::test::run_until;

double total_mass(const Solver<1>& s) {
  double m = 0.0;
  for (double mp : s.particles.mass) m += mp;
  return m;
}

// Fixed-free bar, v(x,0) = v0 sin(beta x): the centre-of-mass velocity is
// v0/(beta L) cos(omega t) with beta = pi/(2L), omega = beta c.
// The largest error of the centre-of-mass velocity over four periods, relative to its amplitude.
double axial_vibration_error(ShapeKind shape, UpdateScheme update) {
  Scene scene = test::load_data_scene("bar_vibration_1d.json");
  scene.shape = shape;
  EXPECT_EQ(scene.update, UpdateScheme::musl);
  scene.update = update;
  Solver<1> s(scene);
  const double L = 25.0, v0 = 0.1, c = std::sqrt(100.0 / 1.0);
  const double beta = std::numbers::pi / (2.0 * L), omega = beta * c;
  const double amplitude = v0 / (beta * L);
  const double period = 2.0 * std::numbers::pi / omega;
  const double mass = total_mass(s);
  double worst = 0.0;
  run_until(s, scene, 4.0 * period, [&](double t, double) {
    const double v_cm = s.momentum()[0] / mass;
    worst = std::max(worst, std::abs(v_cm - amplitude * std::cos(omega * t)));
  });
  return worst / amplitude;
}

class AxialVibration : public ::testing::TestWithParam<const char*> {};

TEST_P(AxialVibration, CentreOfMassVelocityWithinTwoPercentOverFourPeriods) {
  const ShapeKind shape = GetParam() == std::string("linear") ? ShapeKind::linear
                          : GetParam() == std::string("gimp") ? ShapeKind::gimp
                                                              : ShapeKind::bspline2;
  const double error = axial_vibration_error(shape, UpdateScheme::musl);
  RecordProperty("max_relative_error", std::to_string(error));
  EXPECT_LT(error, 0.02) << GetParam();
}

// MLS-MPM (the quadratic B-spline only) meets the same bound, as does USL with that kernel.
TEST(AxialVibrationMls, CentreOfMassVelocityWithinTwoPercentOverFourPeriods) {
  for (const UpdateScheme update : {UpdateScheme::mls, UpdateScheme::usl}) {
    const double error = axial_vibration_error(ShapeKind::bspline2, update);
    RecordProperty(
        update == UpdateScheme::mls ? "mls_max_relative_error" : "usl_max_relative_error",
        std::to_string(error));
    EXPECT_LT(error, 0.02) << (update == UpdateScheme::mls ? "mls" : "usl");
  }
}

INSTANTIATE_TEST_SUITE_P(AllShapes, AxialVibration,
                         ::testing::Values("linear", "gimp", "bspline2"));

// Steel bar hitting a rigid wall on a grid line: the wall stress is rho c v0 for 2L/c, then the
// bar leaves at -v0 (elastic wave theory).
struct ImpactResult {
  double plateau = 0.0;       ///< mean wall stress over the middle 60% of the contact
  double contact_time = 0.0;  ///< time the wall stress exceeds half the plateau
  double rebound = 0.0;       ///< centre-of-mass velocity after contact
};

ImpactResult bar_impact(ShapeKind shape, UpdateScheme update = UpdateScheme::musl) {
  Scene scene = test::load_data_scene("bar_impact_1d.json");
  scene.shape = shape;
  scene.update = update;
  Solver<1> s(scene);
  const double c = std::sqrt(2.0e11 / 7850.0), L = 1.0;
  const double duration = 2.0 * L / c, sigma0 = 7850.0 * c * 1.0;
  double plateau_sum = 0.0, plateau_time = 0.0, first = -1.0, last = -1.0;
  run_until(s, scene, scene.end_time, [&](double t, double dt) {
    const double stress = s.wall_impulses()[0][0] / dt;  // impulse on the material, +x
    s.reset_wall_impulses();
    if (stress > 0.5 * sigma0) {
      if (first < 0) first = t - dt;
      last = t;
    }
    if (t > 0.2 * duration && t < 0.8 * duration) {
      plateau_sum += stress * dt;
      plateau_time += dt;
    }
  });
  return {plateau_sum / plateau_time / sigma0, last - first, s.momentum()[0] / total_mass(s)};
}

TEST(BarImpact, PlateauContactTimeAndReboundMatchWaveTheory) {
  const double c = std::sqrt(2.0e11 / 7850.0), h = 0.01;
  for (ShapeKind shape : {ShapeKind::linear, ShapeKind::gimp, ShapeKind::bspline2}) {
    const ImpactResult r = bar_impact(shape);
    EXPECT_NEAR(r.plateau, 1.0, 0.05) << to_string(shape);
    EXPECT_NEAR(r.contact_time, 2.0 / c, 2.0 * h / c) << to_string(shape);
    EXPECT_NEAR(r.rebound, 1.0, 0.05) << to_string(shape);
  }
  const ImpactResult mls = bar_impact(ShapeKind::bspline2, UpdateScheme::mls);
  EXPECT_NEAR(mls.plateau, 1.0, 0.05) << "mls";
  EXPECT_NEAR(mls.contact_time, 2.0 / c, 2.0 * h / c) << "mls";
  EXPECT_NEAR(mls.rebound, 1.0, 0.05) << "mls";
}

// An elastic block dropped onto the floor: before it touches, total energy (kinetic + strain +
// gravitational) stays constant.
void block_drop_energy(const Scene& scene) {
  Solver<3> s(scene);
  const double gap = scene.bodies[0].min[2] - scene.box_min[2];
  // The kernel reaches 1.5 h below the lowest particle row (h/4 below the block face).
  const double reach = gap - 1.5 * scene.spacing;
  const double t_touch = std::sqrt(2.0 * reach / 9.81);
  const double e0 = s.energies().total();
  double mass = 0.0;
  for (double m : s.particles.mass) mass += m;
  const double converted = mass * 9.81 * reach;  // potential energy turned into motion
  double worst = 0.0;
  run_until(s, scene, 0.98 * t_touch,
            [&](double, double) { worst = std::max(worst, std::abs(s.energies().total() - e0)); });
  EXPECT_LT(worst, 0.05 * converted);
  EXPECT_GT(s.energies().kinetic, 0.9 * converted);
}

TEST(BlockDrop3D, ConservesEnergyBeforeImpact) {
  for (const UpdateScheme update : {UpdateScheme::musl, UpdateScheme::mls}) {
    SCOPED_TRACE(update == UpdateScheme::mls ? "mls" : "musl");
    Scene scene = test::load_data_scene("block_drop_3d.json");
    scene.update = update;
    block_drop_energy(scene);
  }
}

// A thin elastic sheet sliding on a Coulomb floor (grid-face wall, mu = 0.5) at v0 = 1 m/s stops
// after v0^2 / (2 mu g) = 0.1019 m, also when it is one particle thick: the floor's friction acts
// on the nodes the sheet's particles weigh on, whatever their share (docs/validation.md: the
// thin front of a granular collapse is not carried on by a weakened basal friction). 2%: the
// sheet's own elastic shear moves its centroid by a fraction of that (measured within 0.7%), the
// stop is resolved to a time step (v0 dt ~ 1e-4 m).
TEST(SlidingSheet, StopsAtTheCoulombDistanceWhenOneParticleThick) {
  const double mu = 0.5, v0 = 1.0, g = 9.81, h = 0.1 / 16;
  for (const int rows : {1, 2, 4}) {
    nlohmann::json doc = test::box_scene(2, "bspline2", h);
    const double thick = rows * h / 2;  // 2 x 2 particles per cell
    doc["grid"]["max"] = {0.5, h * std::ceil((thick + 0.05) / h)};
    doc["gravity"] = {0.0, -g};
    doc["materials"][0]["density"] = 1600.0;
    doc["materials"][0]["youngs_modulus"] = 2.0e6;
    doc["bodies"][0]["shape"]["min"] = {0.05, 0.0};
    doc["bodies"][0]["shape"]["max"] = {0.15, thick};
    doc["bodies"][0]["velocity"] = {v0, 0.0};
    doc["walls"] = {{{"face", "ymin"}, {"condition", "friction"}, {"mu", mu}, {"separable", true}}};
    const Scene scene = test::parse(doc);
    Solver<2> s(scene);
    auto centroid = [&]() {
      double mx = 0.0, m = 0.0;
      for (std::size_t p = 0; p < s.particles.size(); ++p) {
        mx += s.particles.mass[p] * s.particles.position[p][0];
        m += s.particles.mass[p];
      }
      return mx / m;
    };
    const double start = centroid();
    run_until(s, scene, 2.0 * v0 / (mu * g), [](double, double) {});  // twice the stop time
    const double exact = v0 * v0 / (2.0 * mu * g);
    EXPECT_NEAR((centroid() - start) / exact, 1.0, 0.02) << rows << " particle rows";
    double fastest = 0.0;
    for (const auto& v : s.particles.velocity) fastest = std::max(fastest, v.norm());
    EXPECT_LT(fastest, 1e-3 * v0) << rows << " particle rows";
  }
}

}  // namespace
}  // namespace mpm
