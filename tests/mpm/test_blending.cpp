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
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <functional>
#include <limits>
#include <numbers>
#include <numeric>
#include <optional>
#include <string>
#include <tuple>
#include <utility>
#include <vector>

#include <tbb/global_control.h>
#include <Eigen/Geometry>
#include <nlohmann/json.hpp>

#include "mpm/solver.hpp"
#include "perf_scenes.hpp"  // bench/
#include "support/run_until.hpp"

namespace mpm {
namespace {

using nlohmann::json;

constexpr double kGravity = 9.81;
/// A particle centre may sit at most this many grid spacings behind the wall. The wall acts on
/// node velocities, so a particle drifts through only by the interpolation error of its normal
/// velocity over a step; 0.05 h is a fifth of the h/4 of material a particle carries in front
/// of its centre (2 particles per cell), so anything beyond it means the wall leaks, not
/// round-off.
constexpr double kBehindTolerance = 0.05;

using mpm::test::run_until;

template <int D>
double total_mass(const Solver<D>& s) {
  double m = 0.0;
  for (double mp : s.particles.mass) m += mp;
  return m;
}

template <int D>
Vec<D> centre_of_mass(const Solver<D>& s) {
  Vec<D> x = Vec<D>::Zero();
  for (std::size_t p = 0; p < s.particles.size(); ++p) {
    x += s.particles.mass[p] * s.particles.position[p];
  }
  return x / total_mass(s);
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

/// Separable contact: frictionless slip, or Coulomb friction for mu > 0.
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

/// A dual-grid wall's method: a scene method name, or "mortar_coarse": mortar with Phi's
/// multipliers merged within one cell spacing along the surface ("multiplier_radius": 1).
void set_method(json& wall, const std::string& method) {
  if (method == "mortar_coarse") {
    wall["method"] = "mortar";
    wall["multiplier_radius"] = 1.0;
  } else {
    wall["method"] = method;
  }
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

/// Points of a straight wall from origin + u0 * dir to origin + u1 * dir in segments of about
/// `segment` (a single segment if it is longer than the wall), as a JSON polyline.
json polyline_json(const Eigen::Vector2d& origin, const Eigen::Vector2d& dir, double u0, double u1,
                   double segment) {
  const int segments = std::max(1, static_cast<int>(std::lround((u1 - u0) / segment)));
  json points = json::array();
  for (int i = 0; i <= segments; ++i) {
    const Eigen::Vector2d x = origin + (u0 + (u1 - u0) * i / segments) * dir;
    points.push_back(json::array({x.x(), x.y()}));
  }
  return points;
}

/// Grid box around a set of points, `margin` cells beyond them, on multiples of h.
std::pair<Eigen::VectorXd, Eigen::VectorXd> grid_box(const std::vector<Eigen::VectorXd>& points,
                                                     double h, int margin) {
  Eigen::VectorXd lo = points.front(), hi = points.front();
  for (const auto& x : points) {
    lo = lo.cwiseMin(x);
    hi = hi.cwiseMax(x);
  }
  for (Eigen::Index d = 0; d < lo.size(); ++d) {
    lo[d] = h * (std::floor(lo[d] / h) - margin);
    hi[d] = h * (std::ceil(hi[d] / h) + margin);
  }
  return {lo, hi};
}

/// A straight 2D wall through (0.013, 0.027) falling at theta below the x axis: its downhill
/// unit vector, its normal into the material, and the grid box (margin 4 cells of h) around the
/// strip from u0 to u1 along it and `depth` above it.
struct Slope2D {
  Eigen::Vector2d origin{0.013, 0.027}, along, normal;
  Eigen::VectorXd lo, hi;
};

Slope2D slope_2d(double theta, double u0, double u1, double depth, double h) {
  Slope2D s;
  s.along = Eigen::Vector2d(std::cos(theta), -std::sin(theta));
  s.normal = Eigen::Vector2d(std::sin(theta), std::cos(theta));
  std::tie(s.lo, s.hi) =
      grid_box({Eigen::VectorXd(s.origin + u0 * s.along), Eigen::VectorXd(s.origin + u1 * s.along),
                Eigen::VectorXd(s.origin + u0 * s.along + depth * s.normal),
                Eigen::VectorXd(s.origin + u1 * s.along + depth * s.normal)},
               h, 4);
  return s;
}

// ---------------------------------------------------------------------------------------------
// 1D: steel bar (E = 200 GPa, rho = 7850, L = 1, v0 = 1) against a rigid wall. Exact: wall
// stress rho c v0 for 2L/c, then the bar leaves at +v0.

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
         {"shape",
          {{"type", "segment"}, {"min", json::array({x0})}, {"max", json::array({x0 + 1.0})}}},
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
  double min_distance = 0.0;         ///< smallest x_p - x_wall over the run, / h
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
  std::printf(
      "max |f_mortar - f_standard| / sigma0 = %.3e (standard vs exact on the plateau: %.3e)\n",
      worst, worst_exact);
  // Same discretisation: the histories agree to round-off, far inside the discretisation error
  // (the standard run's own deviation from the exact step).
  EXPECT_LT(worst, 1e-6);
  EXPECT_LT(worst, 0.01 * worst_exact);
  EXPECT_NEAR(mortar.plateau, standard.plateau, 1e-6);
  EXPECT_NEAR(mortar.contact_time, standard.contact_time, 1e-12);
  EXPECT_NEAR(mortar.rebound, standard.rebound, 1e-6);
  // And both meet the exact answer.
  for (const BarResult* r : {&standard, &mortar}) {
    EXPECT_NEAR(r->plateau, 1.0, 0.05);
    EXPECT_NEAR(r->contact_time, kBarDuration, 2.0 * kBarH / kBarC);
    EXPECT_NEAR(r->rebound, 1.0, 0.05);
    EXPECT_GE(r->min_distance, -kBehindTolerance);
  }
  std::printf("took %.2f s\n", seconds_since(start));
}

// Enhanced with the wall on a grid line: the enhancement is the standard tent of the wall node
// on the material side (linearly dependent on the standard basis), so it is dropped
// (scheme.dependence_tolerance) and the wall acts through its Gamma multiplier on the standard
// grid alone. That is standard MPM's wall up to how the node is held (a multiplier on
// R^A v^A instead of setting the node's velocity), so the answer must agree with standard MPM
// within standard MPM's own discretisation error.
TEST(EnhancedBar1D, WallOnGridLineMatchesStandardMpm) {
  const auto start = std::chrono::steady_clock::now();
  const json box_wall = {{"face", "xmin"}, {"condition", "slip"}, {"separable", true}};
  const BarResult standard = bar_impact(bar_scene(0.2, 0.2, box_wall, "linear"), 0.2, 0.0);
  const BarResult enhanced = bar_impact(
      bar_scene(0.0, 0.2, dual_point_wall(0.2, "enhanced", kBarH, 1), "linear"), 0.2, 0.0);
  ASSERT_EQ(standard.time.size(), enhanced.time.size());
  double worst = 0.0;
  for (std::size_t i = 0; i < standard.time.size(); ++i) {
    worst = std::max(worst, std::abs(standard.stress[i] - enhanced.stress[i]));
  }
  std::printf(
      "standard: plateau %.6f contact %.6f rebound %.6f; enhanced: %.6f %.6f %.6f; max "
      "|f_e - f_s| / sigma0 = %.3e\n",
      standard.plateau, standard.contact_time / kBarDuration, standard.rebound, enhanced.plateau,
      enhanced.contact_time / kBarDuration, enhanced.rebound, worst);
  RecordProperty("max_force_difference_over_sigma0", std::to_string(worst));
  // Standard MPM's own errors against the exact answer bound the difference.
  EXPECT_LE(std::abs(enhanced.plateau - standard.plateau),
            std::max(std::abs(standard.plateau - 1.0), 1e-3));
  EXPECT_LE(std::abs(enhanced.rebound - standard.rebound), std::abs(standard.rebound - 1.0));
  EXPECT_LE(std::abs(enhanced.contact_time - standard.contact_time), 2.0 * kBarH / kBarC);
  EXPECT_GE(enhanced.min_distance, -kBehindTolerance);
  std::printf("took %.2f s\n", seconds_since(start));
}

// The wall swept across one grid cell in 20 steps (mortar, layer thickness h): the plateau and
// the rebound must meet the exact answer at every offset, for every shape function. The contact
// time (wall stress above half the plateau) must be within 2h/c of 2L/c for the linear kernel
// of the talk; for GIMP and B-splines it is recorded, not asserted: their wider stencils release
// the bar gradually over ~2% of 2L/c, and with bspline2 the half-height duration at offset 0.2 h
// is 0.9897 * 2L/c, one step (0.25% of 2L/c) beyond the bound, while the plateau is within 0.6%.
/// (method, shape function): Blending (mortar) and Enhanced meet the same bounds.
class BlendingBarSweep : public ::testing::TestWithParam<std::tuple<const char*, const char*>> {};

TEST_P(BlendingBarSweep, PlateauContactAndReboundAtTwentyOffsets) {
  const auto start = std::chrono::steady_clock::now();
  const std::string method = std::get<0>(GetParam());
  const std::string shape = std::get<1>(GetParam());
  double worst_plateau = 0.0, worst_contact = 0.0, worst_rebound = 0.0;
  for (int k = 0; k < 20; ++k) {
    const double offset = k / 20.0;
    const double xw = 0.2 + offset * kBarH;
    const BarResult r =
        bar_impact(bar_scene(0.0, 0.2, dual_point_wall(xw, method, kBarH, 1), shape), xw, xw - 0.2);
    std::printf(
        "%s %s offset %.2f h: plateau %.5f contact %.5f (2L/c) rebound %.5f min distance "
        "%+.4f h\n",
        method.c_str(), shape.c_str(), offset, r.plateau, r.contact_time / kBarDuration, r.rebound,
        r.min_distance);
    EXPECT_NEAR(r.plateau, 1.0, 0.05) << shape << " offset " << offset;
    if (shape == "linear") {
      EXPECT_NEAR(r.contact_time, kBarDuration, 2.0 * kBarH / kBarC) << "offset " << offset;
    }
    EXPECT_NEAR(r.rebound, 1.0, 0.05) << shape << " offset " << offset;
    EXPECT_GE(r.min_distance, -kBehindTolerance) << shape << " offset " << offset;
    worst_plateau = std::max(worst_plateau, std::abs(r.plateau - 1.0));
    worst_contact = std::max(worst_contact, std::abs(r.contact_time / kBarDuration - 1.0));
    worst_rebound = std::max(worst_rebound, std::abs(r.rebound - 1.0));
  }
  RecordProperty("worst_plateau_error", std::to_string(worst_plateau));
  RecordProperty("worst_contact_time_error", std::to_string(worst_contact));
  RecordProperty("worst_rebound_error", std::to_string(worst_rebound));
  std::printf("%s: worst plateau error %.4f, contact time error %.4f, rebound error %.4f\n",
              shape.c_str(), worst_plateau, worst_contact, worst_rebound);
  std::printf("took %.2f s\n", seconds_since(start));
}

/// Test name of a method parameter: "one-way" is spelt one_way.
std::string method_name(const ::testing::TestParamInfo<const char*>& p) {
  std::string name = p.param;
  std::ranges::replace(name, '-', '_');
  return name;
}

/// Test name of a (method, shape function) parameter: "one-way" is spelt one_way.
std::string method_and_shape_name(
    const ::testing::TestParamInfo<std::tuple<const char*, const char*>>& p) {
  std::string name = std::string(std::get<0>(p.param)) + "_" + std::get<1>(p.param);
  std::ranges::replace(name, '-', '_');
  return name;
}

INSTANTIATE_TEST_SUITE_P(MethodAndShape, BlendingBarSweep,
                         ::testing::Combine(::testing::Values("mortar", "enhanced"),
                                            ::testing::Values("linear", "gimp", "bspline2")),
                         method_and_shape_name);

// ---------------------------------------------------------------------------------------------
// Free flight across Phi: a block with a non-uniform velocity (a standing wave on a drift away
// from the wall) starts inside the layer, clear of the wall's own cells, and leaves through Phi.
// Nothing acts on it but its own stress and the interface coupling, so the total momentum must
// keep its initial value: mortar's interface impulses are equal and opposite, one-way's are not
// (it only corrects the standard grid).
//
// The scenes set the standard solver's mass_threshold to 0: with the default (1e-9 of the mean
// particle mass) standard MPM itself drops the momentum given to nearly empty B-spline nodes,
// ~1e-9 relative over this run with no wall at all, which would hide the coupling's own error.

struct FreeFlight {
  double momentum_error = 0.0;   ///< max |P(t) - P(0)| / |P(0)| over the run
  double grid_mass_error = 0.0;  ///< max |sum of both grids' nodal masses - particle mass| / mass
  double wall_impulse = 0.0;     ///< max |impulse from the wall| over the run (must stay 0)
  std::size_t max_layer_particles = 0, final_layer_particles = 0;
  double min_distance = 0.0;  ///< smallest signed distance to the wall / h
};

template <int D>
FreeFlight free_flight(const json& doc, const Vec<D>& origin, const Vec<D>& normal) {
  const Scene scene = parse_scene(doc, "<free flight>");
  Solver<D> s(scene);
  const double mass = total_mass(s);
  const Eigen::Vector3d p0 = s.momentum();
  FreeFlight r;
  r.min_distance = min_signed_distance<D>(s, origin, normal) / scene.spacing;
  run_until(s, scene, scene.end_time, [&](double, double) {
    r.momentum_error = std::max(r.momentum_error, (s.momentum() - p0).norm() / p0.norm());
    // This step's nodal masses: each particle must have been given to exactly one grid
    // (Blending) or to the standard grid (Enhanced: the boundary grid only adds to it).
    double grid_mass = 0.0;
    for (std::size_t n = 0; n < s.grid.size(); ++n) grid_mass += s.grid.mass[n];
    for (const auto& w : s.dual_walls()) {
      if (w.enhanced) continue;
      for (double m : w.mass) grid_mass += m;
    }
    r.grid_mass_error = std::max(r.grid_mass_error, std::abs(grid_mass - mass) / mass);
    r.wall_impulse = std::max(r.wall_impulse, s.wall_impulses()[0].norm());
    r.max_layer_particles = std::max(r.max_layer_particles, s.dual_walls()[0].layer_particles);
    r.final_layer_particles = s.dual_walls()[0].layer_particles;
    r.min_distance =
        std::min(r.min_distance, min_signed_distance<D>(s, origin, normal) / scene.spacing);
  });
  return r;
}

/// Soft elastic material (c ~ 10 m/s) so that the block crosses the layer in a few hundred
/// steps.
json soft_material() {
  return {{"name", "soft"},
          {"model", "linear_elastic"},
          {"density", 1000.0},
          {"youngs_modulus", 1.0e5},
          {"poisson_ratio", 0.3}};
}

/// 1D: wall at 0.2 (material at x > 0.2), layer 3h in three cells; the bar starts 1.5h from the
/// wall (in the second cell, so Gamma's cell is empty) and drifts out at 0.2 +- 0.1 m/s.
json free_flight_1d(const std::string& method) {
  const double h = 0.01, x0 = 0.2 + 1.5 * h, L = 0.3;
  return {
      {"dimension", 1},
      {"grid", {{"min", json::array({0.0})}, {"max", json::array({1.0})}, {"spacing", h}}},
      {"shape_function", "linear"},
      {"scheme",
       {{"update", "musl"}, {"transfer", "flip"}, {"flip_blend", 1.0}, {"mass_threshold", 0.0}}},
      {"materials", json::array({soft_material()})},
      {"bodies",
       {{{"name", "bar"},
         {"material", "soft"},
         {"shape",
          {{"type", "segment"}, {"min", json::array({x0})}, {"max", json::array({x0 + L})}}},
         {"particles_per_cell", 2},
         {"velocity", json::array({0.2})},
         {"velocity_sine",
          {{"amplitude", json::array({0.1})},
           {"wavenumber", 2.0 * std::numbers::pi / L},
           {"origin", x0}}}}}},
      {"walls", json::array({dual_point_wall(0.2, method, 3.0 * h, 3)})},
      {"time", {{"end", 0.1}, {"cfl", 0.5}}},
  };
}

/// 2D: a wall at 30 degrees to the grid (segments of h), layer 3h in three cells; a block
/// rotated to lie parallel to it starts 1.2h above it and leaves obliquely (0.2 m/s away from
/// the wall, 0.4 m/s along it) with a standing wave of 0.1 m/s on top. Quadratic B-splines,
/// MUSL, `transfer` "apic" or "flip".
struct FreeFlight2D {
  json doc;
  Eigen::Vector2d origin, normal;
};

FreeFlight2D free_flight_2d(const std::string& method, const std::string& transfer) {
  const double h = 0.05, theta_deg = 30.0, theta = theta_deg * std::numbers::pi / 180.0;
  const Slope2D slope = slope_2d(theta, -0.5, 0.8, 0.6, h);
  const auto& [origin, along, normal, lo, hi] = slope;
  const double a = 0.3, b = 0.2;
  const Eigen::Vector2d centre = origin + (1.2 * h + 0.5 * b) * normal;
  const Eigen::Vector2d velocity = 0.2 * normal + 0.4 * along;
  json wall = contact_json(0.0);
  wall["name"] = "wall";
  wall["surface"] = {{"type", "polyline"}, {"points", polyline_json(origin, along, -0.5, 0.8, h)}};
  set_method(wall, method);
  wall["thickness"] = 3.0 * h;
  wall["layers"] = 3;
  json scheme = {{"update", "musl"}, {"transfer", transfer}, {"mass_threshold", 0.0}};
  json doc = {
      {"dimension", 2},
      {"grid", {{"min", vec_json(lo)}, {"max", vec_json(hi)}, {"spacing", h}}},
      {"shape_function", "bspline2"},
      {"scheme", scheme},
      {"materials", json::array({soft_material()})},
      {"bodies",
       {{{"name", "block"},
         {"material", "soft"},
         {"shape",
          {{"type", "box"},
           {"min", json::array({centre.x() - 0.5 * a, centre.y() - 0.5 * b})},
           {"max", json::array({centre.x() + 0.5 * a, centre.y() + 0.5 * b})},
           {"rotation", -theta_deg}}},
         {"particles_per_cell", 2},
         {"velocity", json::array({velocity.x(), velocity.y()})},
         {"velocity_sine",
          {{"amplitude", json::array({0.1, 0.05})},
           {"wavenumber", 2.0 * std::numbers::pi / a},
           {"origin", centre.x()}}}}}},
      {"walls", json::array({wall})},
      {"time", {{"end", 0.6}, {"cfl", 0.5}}},
  };
  return {doc, origin, normal};
}

void report_free_flight(const char* label, const FreeFlight& r) {
  std::printf(
      "%s: momentum error %.3e, grid mass error %.3e, wall impulse %.3e, layer particles "
      "max %zu final %zu, min distance %+.3f h\n",
      label, r.momentum_error, r.grid_mass_error, r.wall_impulse, r.max_layer_particles,
      r.final_layer_particles, r.min_distance);
}

/// The run really is a crossing without contact: particles start in the layer and all leave it,
/// the wall never acts, and nothing goes behind it.
void expect_clean_crossing(const FreeFlight& r) {
  EXPECT_GT(r.max_layer_particles, 0U);
  EXPECT_EQ(r.final_layer_particles, 0U);
  EXPECT_EQ(r.wall_impulse, 0.0);
  EXPECT_GE(r.min_distance, -kBehindTolerance);
}

/// A conserving method (mortar, enhanced): the crossing is clean and mass and momentum are kept
/// to round-off, in 1D and in 2D with APIC and FLIP.
void expect_conserving_free_flight_1d(const std::string& method) {
  const auto start = std::chrono::steady_clock::now();
  const FreeFlight r = free_flight<1>(free_flight_1d(method), Vec<1>(0.2), Vec<1>(1.0));
  report_free_flight(("1D " + method).c_str(), r);
  ::testing::Test::RecordProperty("momentum_error", std::to_string(r.momentum_error));
  expect_clean_crossing(r);
  EXPECT_LT(r.grid_mass_error, 1e-10);
  EXPECT_LT(r.momentum_error, 1e-10);
  std::printf("took %.2f s\n", seconds_since(start));
}

void expect_conserving_free_flight_2d(const std::string& method) {
  const auto start = std::chrono::steady_clock::now();
  for (const char* transfer : {"apic", "flip"}) {
    const FreeFlight2D scene = free_flight_2d(method, transfer);
    const FreeFlight r = free_flight<2>(scene.doc, scene.origin, scene.normal);
    report_free_flight(("2D " + method + " " + transfer).c_str(), r);
    ::testing::Test::RecordProperty(std::string("momentum_error_") + transfer,
                                    std::to_string(r.momentum_error));
    expect_clean_crossing(r);
    EXPECT_LT(r.grid_mass_error, 1e-10) << transfer;
    EXPECT_LT(r.momentum_error, 1e-10) << transfer;
  }
  std::printf("took %.2f s\n", seconds_since(start));
}

TEST(BlendingFreeFlight, MortarConservesMassAndMomentum1D) {
  expect_conserving_free_flight_1d("mortar");
}

TEST(BlendingFreeFlight, MortarConservesMassAndMomentum2D) {
  expect_conserving_free_flight_2d("mortar");
}

// Merged multipliers keep the partition of unity over Phi, so the impulses stay equal and opposite.
TEST(BlendingFreeFlight, MortarWithMergedMultipliersConservesMassAndMomentum2D) {
  expect_conserving_free_flight_2d("mortar_coarse");
}

// Enhanced: the cross mass keeps the lumped rows' sums (the uniform mode), so the superposed
// field carries exactly the particles' momentum across the layer and out through Phi.
TEST(EnhancedFreeFlight, ConservesMassAndMomentum1D) {
  expect_conserving_free_flight_1d("enhanced");
}

TEST(EnhancedFreeFlight, ConservesMassAndMomentum2D) {
  expect_conserving_free_flight_2d("enhanced");
}

// One-way prescribes the boundary grid's velocity on the standard grid and never lets the
// boundary grid feel the reaction: the interface impulses do not balance, and momentum is not
// conserved (the finding of docs/blending.md: 0.28 relative in 1D, 0.14 in 2D with FLIP, against
// 1e-15 for mortar). Asserted here so a change that makes one-way conservative is noticed.
// A lone stiff particle (an h/2 square, E = 2 MPa) thrown at a frictionless separable wall at
// 37 degrees to the grid. A rigid wall can only take energy away, and an elastic body rebounds
// at most at its approach speed (restitution <= 1): E(t) <= E(0) and v_n after <= v_n before.
// Before the wall acted only on touch and the layer's MUSL remap left C_p out, mortar threw it
// back at 2.2 times its approach speed with 6.7 times its energy.
class LoneParticle : public ::testing::TestWithParam<const char*> {};

TEST_P(LoneParticle, StiffParticleAgainstWallNeverGainsEnergy) {
  const double h = 0.05, theta = 37.0 * std::numbers::pi / 180.0;
  const Slope2D slope = slope_2d(theta, -0.2, 1.2, 0.5, h);
  const auto& [origin, along, normal, lo, hi] = slope;
  const Eigen::Vector2d centre = origin + 0.5 * along + 2.0 * h * normal;
  const Eigen::Vector2d velocity = -1.0 * normal + 1.0 * along;
  json wall = contact_json(0.0);
  wall["name"] = "wall";
  wall["surface"] = {{"type", "polyline"}, {"points", polyline_json(origin, along, -0.2, 1.2, h)}};
  set_method(wall, GetParam());
  json doc = {
      {"dimension", 2},
      {"grid", {{"min", vec_json(lo)}, {"max", vec_json(hi)}, {"spacing", h}}},
      {"shape_function", "bspline2"},
      {"scheme", {{"update", "musl"}, {"transfer", "apic"}}},
      {"materials", json::array({{{"name", "m"},
                                  {"model", "neo_hookean"},
                                  {"density", 1000.0},
                                  {"youngs_modulus", 2e6},
                                  {"poisson_ratio", 0.3}}})},
      {"bodies",
       {{{"material", "m"},
         {"shape",
          {{"type", "box"},
           {"min", json::array({centre.x() - 0.25 * h, centre.y() - 0.25 * h})},
           {"max", json::array({centre.x() + 0.25 * h, centre.y() + 0.25 * h})},
           {"rotation", -37.0}}},
         {"particles_per_cell", 1},
         {"velocity", json::array({velocity.x(), velocity.y()})}}}},
      {"walls", json::array({wall})},
      {"time", {{"end", 0.3}, {"cfl", 0.4}}},
  };
  const Scene scene = parse_scene(doc, "<lone particle>");
  Solver<2> s(scene);
  ASSERT_EQ(s.particles.size(), 1u);
  const double e0 = s.energies().total();
  double worst = 0.0, min_distance = 1.0;
  run_until(s, scene, scene.end_time, [&](double, double) {
    worst = std::max(worst, s.energies().total() / e0);
    min_distance = std::min(min_distance, min_signed_distance<2>(s, origin, normal) / h);
  });
  const Eigen::Vector2d v = s.particles.velocity[0];
  std::printf("%s: max E/E0 %.4f, v_n after %.4f (approach 1), v_t %.4f, min distance %.3f h\n",
              GetParam(), worst, v.dot(normal), v.dot(along), min_distance);
  EXPECT_LE(worst, 1.0 + 1e-9);
  EXPECT_LE(std::abs(v.dot(normal)), 1.0);
  EXPECT_GE(min_distance, -kBehindTolerance);
}

INSTANTIATE_TEST_SUITE_P(Method, LoneParticle,
                         ::testing::Values("mortar", "mortar_coarse", "enhanced"),
                         [](const auto& param_info) { return std::string(param_info.param); });

TEST(BlendingFreeFlight, OneWayDoesNotConserveMomentum1D) {
  const auto start = std::chrono::steady_clock::now();
  const FreeFlight r = free_flight<1>(free_flight_1d("one-way"), Vec<1>(0.2), Vec<1>(1.0));
  report_free_flight("1D one-way", r);
  RecordProperty("momentum_error", std::to_string(r.momentum_error));
  EXPECT_TRUE(std::isfinite(r.momentum_error));
  EXPECT_GT(r.momentum_error, 1e-3);
  EXPECT_LT(r.grid_mass_error, 1e-10);
  expect_clean_crossing(r);
  std::printf("took %.2f s\n", seconds_since(start));
}

// Same in 2D with FLIP. With APIC at CFL 0.5, one-way is unstable on this scene (velocities grow
// from 0.5 to ~6 m/s between t = 0.12 and 0.37 s and a particle inverts, at wall angles 0, 10, 30
// and 45 degrees alike; finite at CFL 0.25 with a momentum error ~1): recorded in
// docs/blending.md as a failure of the one-way method, which mortar (stable here) replaces.
TEST(BlendingFreeFlight, OneWayDoesNotConserveMomentum2D) {
  const auto start = std::chrono::steady_clock::now();
  const FreeFlight2D scene = free_flight_2d("one-way", "flip");
  const FreeFlight r = free_flight<2>(scene.doc, scene.origin, scene.normal);
  report_free_flight("2D one-way flip", r);
  RecordProperty("momentum_error", std::to_string(r.momentum_error));
  EXPECT_TRUE(std::isfinite(r.momentum_error));
  EXPECT_GT(r.momentum_error, 1e-3);
  EXPECT_LT(r.grid_mass_error, 1e-10);
  expect_clean_crossing(r);
  std::printf("took %.2f s\n", seconds_since(start));
}

// ---------------------------------------------------------------------------------------------
// Block on an incline at angle theta (gravity along -y in 2D, -z in 3D), mortar, MUSL/APIC,
// quadratic B-splines, h = 0.05, 2 particles per cell. Exact: the centre of mass moves
// d = a t^2 / 2 downhill with a = g (sin theta - mu cos theta) (tan theta > mu), stays at rest
// across the incline, and the wall's normal force is m g cos theta.
//
// The angles cover the orientations 8 to 43 degrees to the grid (theta and 90 - theta are mirror
// images for the grid) while keeping tan(theta) well above mu = 0.3: at 20 degrees friction
// cancels 82% of the downhill pull, so a 1% error in the friction impulse is a 5% error in d,
// and standard MPM with a grid-aligned wall (gravity rotated instead) is itself 10.8% off there.

constexpr double kInclineH = 0.05;
constexpr double kInclineTime = 0.3;
constexpr double kInclineAngles[] = {30.0, 36.0, 43.0, 50.0, 58.0, 66.0, 74.0, 82.0};

json incline_doc(int dim, const Eigen::VectorXd& lo, const Eigen::VectorXd& hi, json body,
                 json wall, double cfl) {
  Eigen::VectorXd gravity = Eigen::VectorXd::Zero(dim);
  gravity[dim - 1] = -kGravity;
  return {
      {"dimension", dim},
      {"grid", {{"min", vec_json(lo)}, {"max", vec_json(hi)}, {"spacing", kInclineH}}},
      {"shape_function", "bspline2"},
      {"scheme", {{"update", "musl"}, {"transfer", "apic"}}},
      {"gravity", vec_json(gravity)},
      {"materials",
       {{{"name", "m"},
         {"model", "neo_hookean"},
         {"density", 1000.0},
         {"youngs_modulus", 2.0e6},
         {"poisson_ratio", 0.3}}}},
      {"bodies", json::array({std::move(body)})},
      {"walls", json::array({std::move(wall)})},
      {"time", {{"end", kInclineTime}, {"cfl", cfl}}},
  };
}

json incline_wall(double mu, json surface, const std::string& method) {
  json wall = contact_json(mu);
  wall["name"] = "incline";
  wall["surface"] = std::move(surface);
  set_method(wall, method);
  return wall;
}

/// An incline scene and its frame (padded to 3D): a point of the wall plane, the downhill unit
/// vector and the unit normal into the material.
struct InclineScene {
  json doc;
  Eigen::Vector3d origin, downhill, normal;
};

/// 2D: a straight polyline running downhill (the material on its left) in segments of about
/// `segment`; the block (0.3 x 0.15) rotated to lie flat on it, 1e-6 above it.
/// remesh false: the polyline as given (the reader otherwise cuts it into segments of h).
InclineScene incline_2d(double theta_deg, double mu, double segment, double cfl,
                        const std::string& method, bool remesh = true) {
  const double theta = theta_deg * std::numbers::pi / 180.0;
  const double a = 0.3, b = 0.15, u0 = -0.4, u1 = 0.8;
  const Slope2D slope = slope_2d(theta, u0, u1, 0.5, kInclineH);
  const auto& [origin, s, n, lo, hi] = slope;
  const Eigen::Vector2d centre = origin + (0.5 * b + 1e-6) * n;
  json body = {{"name", "block"},
               {"material", "m"},
               {"shape",
                {{"type", "box"},
                 {"min", json::array({centre.x() - 0.5 * a, centre.y() - 0.5 * b})},
                 {"max", json::array({centre.x() + 0.5 * a, centre.y() + 0.5 * b})},
                 {"rotation", -theta_deg}}},
               {"particles_per_cell", 2}};
  json surface = {{"type", "polyline"},
                  {"points", polyline_json(origin, s, u0, u1, segment)},
                  {"closed", false},
                  {"remesh", remesh}};
  InclineScene out;
  out.doc =
      incline_doc(2, lo, hi, std::move(body), incline_wall(mu, std::move(surface), method), cfl);
  out.origin << origin, 0.0;
  out.downhill << s, 0.0;
  out.normal << n, 0.0;
  return out;
}

/// A temporary folder for mesh files, one per test process, removed at the end of the test.
class TempDir {
 public:
  TempDir()
      : path_(std::filesystem::temp_directory_path() /
              ("mpm_test_blending_" + std::to_string(::getpid()))) {
    std::filesystem::create_directories(path_);
  }
  ~TempDir() {
    std::error_code ec;
    std::filesystem::remove_all(path_, ec);
  }
  TempDir(const TempDir&) = delete;
  TempDir& operator=(const TempDir&) = delete;
  [[nodiscard]] const std::filesystem::path& path() const { return path_; }

 private:
  std::filesystem::path path_;
};

/// 3D: the plane tilted by theta about the horizontal axis (cos 30, sin 30, 0), so that its
/// normal has three non-zero components; a rectangle of it written as two triangles (normals
/// into the material) and remeshed to h by the scene reader. The block (0.3 downhill, 0.2 across,
/// 0.15 thick) is rotated so that its faces lie along the downhill, across and normal
/// directions, 1e-6 above the plane.
/// split > u0: the rectangle is two named parts, "upper" (u0 to split) and "lower" (split to
/// u1), sharing the edge at split.
InclineScene incline_3d(double theta_deg, double mu, const std::filesystem::path& dir,
                        const std::string& method, double split = -1.0) {
  const double theta = theta_deg * std::numbers::pi / 180.0;
  const double phi = 30.0 * std::numbers::pi / 180.0;
  const Eigen::Vector3d axis(std::cos(phi), std::sin(phi), 0.0);
  const Eigen::Vector3d origin(0.013, 0.027, 0.011);
  const Eigen::Vector3d n = Eigen::AngleAxisd(theta, axis) * Eigen::Vector3d::UnitZ();
  const Eigen::Vector3d s = (-Eigen::Vector3d::UnitZ() + n.z() * n).normalized();
  const Eigen::Vector3d t = n.cross(s);
  const double a = 0.3, b = 0.2, c = 0.15, u0 = -0.25, u1 = 0.7, w = 0.2;

  const Eigen::Vector3d corners[4] = {origin + u0 * s - w * t, origin + u1 * s - w * t,
                                      origin + u1 * s + w * t, origin + u0 * s + w * t};
  const std::filesystem::path mesh =
      dir / ("incline_" + std::to_string(static_cast<int>(theta_deg)) + ".obj");
  {
    std::ofstream out(mesh);
    out.precision(17);
    for (const auto& x : corners) out << "v " << x.x() << ' ' << x.y() << ' ' << x.z() << '\n';
    // (b - a) x (c - a) = (u1 - u0) * 2w * (s x t) = +n: into the material.
    if (split > u0) {
      const Eigen::Vector3d edge[2] = {origin + split * s - w * t, origin + split * s + w * t};
      for (const auto& x : edge) {
        out << "v " << x.x() << ' ' << x.y() << ' ' << x.z() << '\n';
      }
      out << "o upper\nf 1 5 6\nf 1 6 4\no lower\nf 5 2 3\nf 5 3 6\n";
    } else {
      out << "f 1 2 3\nf 1 3 4\n";
    }
  }

  std::vector<Eigen::VectorXd> points;
  for (const auto& x : corners) {
    points.emplace_back(x);
    points.emplace_back(x + 0.3 * n);
  }
  auto [lo, hi] = grid_box(points, kInclineH, 2);

  // Box axes (x, y, z) -> (downhill, across, normal), given to the scene as Rz * Ry * Rx.
  Eigen::Matrix3d R;
  R << s, t, n;
  const Eigen::Vector3d zyx = R.eulerAngles(2, 1, 0);
  const Eigen::Vector3d centre = origin + (0.5 * c + 1e-6) * n;
  const double deg = 180.0 / std::numbers::pi;
  json body = {
      {"name", "block"},
      {"material", "m"},
      {"shape",
       {{"type", "box"},
        {"min", json::array({centre.x() - 0.5 * a, centre.y() - 0.5 * b, centre.z() - 0.5 * c})},
        {"max", json::array({centre.x() + 0.5 * a, centre.y() + 0.5 * b, centre.z() + 0.5 * c})},
        {"rotation", json::array({zyx[2] * deg, zyx[1] * deg, zyx[0] * deg})}}},
      {"particles_per_cell", 2}};
  json surface = {{"type", "mesh"}, {"file", mesh.string()}, {"remesh", true}};
  InclineScene out;
  out.doc =
      incline_doc(3, lo, hi, std::move(body), incline_wall(mu, std::move(surface), method), 0.4);
  out.origin = origin;
  out.downhill = s;
  out.normal = n;
  return out;
}

struct InclineResult {
  double displacement = 0.0;    ///< centre-of-mass displacement downhill at the end / exact
  double normal_speed = 0.0;    ///< max |v_cm . n| over the run / (g T)
  double normal_force = 0.0;    ///< mean wall force along n over the run / (m g cos theta)
  double friction_force = 0.0;  ///< mean wall force uphill / (mu m g cos theta), mu > 0
  double min_distance = 0.0;    ///< smallest signed distance to the wall plane / h
  double other_parts = 0.0;     ///< |impulse on the wall's other parts| / T / (m g cos theta)
  double seconds = 0.0;
};

template <int D>
InclineResult run_incline(const InclineScene& in, double theta_deg, double mu) {
  const auto start = std::chrono::steady_clock::now();
  const Scene scene = parse_scene(in.doc, "<incline>");
  Solver<D> s(scene);
  const Vec<D> origin = in.origin.template head<D>(), n = in.normal.template head<D>(),
               downhill = in.downhill.template head<D>();
  // The block's rotation takes its axes to (downhill, [across,] normal), and it was seeded flat
  // on the wall, its bottom row h/4 above it.
  EXPECT_LT((scene.bodies[0].rotation.col(0) - in.downhill).norm(), 1e-9) << theta_deg;
  EXPECT_LT((scene.bodies[0].rotation.col(D - 1) - in.normal).norm(), 1e-9) << theta_deg;
  EXPECT_NEAR(min_signed_distance<D>(s, origin, n) / kInclineH, 0.25, 1e-3) << theta_deg;
  const double mass = total_mass(s);
  const Vec<D> x0 = centre_of_mass(s);
  InclineResult r;
  r.min_distance = std::numeric_limits<double>::infinity();
  double normal_speed = 0.0;
  run_until(s, scene, scene.end_time, [&](double, double) {
    normal_speed = std::max(normal_speed, std::abs(s.momentum().template head<D>().dot(n)) / mass);
    r.min_distance = std::min(r.min_distance, min_signed_distance<D>(s, origin, n) / kInclineH);
  });
  const double theta = theta_deg * std::numbers::pi / 180.0, T = scene.end_time;
  const double accel = kGravity * (std::sin(theta) - mu * std::cos(theta));
  const double normal_load = mass * kGravity * std::cos(theta);
  // The impulse the wall gave the material over the whole run (never reset): its mean is the
  // load, since the block starts and ends at rest across the incline.
  const Eigen::Vector3d impulse = s.wall_impulses()[0];
  r.displacement = (centre_of_mass(s) - x0).dot(downhill) / (0.5 * accel * T * T);
  r.normal_speed = normal_speed / (kGravity * T);
  r.normal_force = impulse.template head<D>().dot(n) / T / normal_load;
  r.friction_force =
      mu > 0.0 ? -impulse.template head<D>().dot(downhill) / T / (mu * normal_load) : 0.0;
  for (std::size_t k = 1; k < s.wall_impulses().size(); ++k) {
    r.other_parts += s.wall_impulses()[k].norm() / T / normal_load;
  }
  r.seconds = seconds_since(start);
  return r;
}

/// The checks on one sweep over kInclineAngles; `label` names it in messages.
void check_incline_sweep(const std::string& label, double mu,
                         const std::vector<InclineResult>& results,
                         double normal_speed_bound = 0.01) {
  double lo = std::numeric_limits<double>::infinity(), hi = -lo, sum = 0.0;
  for (std::size_t i = 0; i < results.size(); ++i) {
    const InclineResult& r = results[i];
    const double theta = kInclineAngles[i];
    std::printf(
        "%s theta %4.1f mu %.1f: d/d_exact %.5f |v_n|max/(gT) %.2e F_n/(mg cos) %.4f "
        "F_t/(mu mg cos) %.4f min distance %+.3f h (%.2f s)\n",
        label.c_str(), theta, mu, r.displacement, r.normal_speed, r.normal_force, r.friction_force,
        r.min_distance, r.seconds);
    EXPECT_NEAR(r.displacement, 1.0, 0.03) << label << " theta " << theta;
    // Supported: with mu = 0 the downhill displacement is that of free fall too, so the block
    // must also stay on the wall. Falling freely it would reach |v_n| = g T cos(theta), at
    // least 0.14 g T at these angles.
    EXPECT_LT(r.normal_speed, normal_speed_bound) << label << " theta " << theta;
    EXPECT_NEAR(r.normal_force, 1.0, 0.03) << label << " theta " << theta;
    EXPECT_GE(r.min_distance, -kBehindTolerance) << label << " theta " << theta;
    lo = std::min(lo, r.displacement);
    hi = std::max(hi, r.displacement);
    sum += r.displacement;
  }
  const double spread = (hi - lo) / (sum / static_cast<double>(results.size()));
  std::printf("%s mu %.1f: spread (max - min) / mean of d/d_exact = %.3e\n", label.c_str(), mu,
              spread);
  ::testing::Test::RecordProperty("spread", std::to_string(spread));
  EXPECT_LT(spread, 0.01) << label;
}

/// (method, mu)
class BlendingIncline : public ::testing::TestWithParam<std::tuple<const char*, double>> {};

void sweep_2d(const std::string& label, double segment, double cfl,
              double normal_speed_bound = 0.01, bool remesh = true) {
  const auto start = std::chrono::steady_clock::now();
  const auto [method, mu] = BlendingIncline::GetParam();
  std::vector<InclineResult> results;
  for (double theta : kInclineAngles) {
    results.push_back(
        run_incline<2>(incline_2d(theta, mu, segment, cfl, method, remesh), theta, mu));
  }
  check_incline_sweep(std::string(method) + " " + label, mu, results, normal_speed_bound);
  std::printf("took %.2f s\n", seconds_since(start));
}

// 2D wall in segments of h (the boundary grid's resolution, as the 3D remesher makes it), CFL
// 0.2; see the next two tests for CFL 0.4.
TEST_P(BlendingIncline, AngleInvariance2D) {
  sweep_2d("2D segments of h, CFL 0.2", kInclineH, 0.2);
}

// The polyline as a user writes a straight incline, its two end points, kept as one boundary-grid
// cell 1.2 m long ("remesh": false), at CFL 0.4.
TEST_P(BlendingIncline, AngleInvariance2DTwoPointWallNotRemeshed) {
  // Enhanced on this wall has two Gamma nodes 1.2 m apart: the enhancement is one linear
  // function along the whole wall and the wall condition holds in the mean over it, so the block
  // settles into the wall by ~0.1 h and its largest normal speed is 0.0117 g T (at 58 degrees,
  // against 0.0045 for mortar, whose Phi coupling sees the standard nodes every h); d and F_n
  // stay within 0.5% and nothing passes the wall. Walls meshed at h (the 3D default, and the
  // other 2D tests) meet 0.01; this case is held to 0.02.
  const bool enhanced = std::string(std::get<0>(GetParam())) == "enhanced";
  sweep_2d("2D two-point wall, CFL 0.4", 10.0, 0.4, enhanced ? 0.02 : 0.01, false);
}

// The same two points as the reader takes them by default (cut into segments of h): the bound
// of the walls meshed at h.
TEST_P(BlendingIncline, AngleInvariance2DTwoPointWallRemeshed) {
  sweep_2d("2D two-point wall remeshed to h, CFL 0.4", 10.0, 0.4);
}

// Segments of h at CFL 0.4. Before stable_dt counted the layer cells at half their size under
// APIC, the block did not stay on the wall here: from t ~ 0.12 s it hopped (|v_n| up to
// 0.14 g T, the bottom row lifted from h/4 to 0.6 h above the wall), the mean normal force
// reached 1.87 m g cos(theta) at 82 degrees and with mu = 0.3 d was 2-4% short, while CFL 0.25
// and 0.2, segments of 0.7 h, and FLIP or PIC at CFL 0.4 were clean. This case guards that limit.
TEST_P(BlendingIncline, AngleInvariance2DSegmentsOfHAtCfl04) {
  sweep_2d("2D segments of h, CFL 0.4", kInclineH, 0.4);
}

TEST_P(BlendingIncline, AngleInvariance3D) {
  const auto start = std::chrono::steady_clock::now();
  const auto [method, mu] = GetParam();
  const TempDir dir;
  std::vector<InclineResult> results;
  for (double theta : kInclineAngles) {
    results.push_back(run_incline<3>(incline_3d(theta, mu, dir.path(), method), theta, mu));
  }
  check_incline_sweep(std::string(method) + " 3D", mu, results);
  std::printf("took %.2f s\n", seconds_since(start));
}

// The boundary grid holds exactly the mass and the first mass moment of the particles its layer
// holds, every step: the alpha basis is a partition of unity that reproduces x (isoparametric),
// so sum_n m_n x_n = sum_p m_p x_p^n to round-off when each pair is summed at its own node.
// A block dropped 0.02 m onto a 20 degree incline with mu 0.5 settles (its particles change
// cell) and then sticks (they keep their cells, and layer_scatter() keeps its sort by cell):
// both paths are checked, and the test counts, from the wall's own locator, that both ran. A
// sort kept after a particle changed cell sums that particle's pairs at its old cell's nodes,
// and the moment no longer matches (the check for a changed cell removed: off by 0.5 m h in 2D;
// 3D fails as well). Bounds 1e-12 of m and of m h: round-off gives about 1e-15 (measured
// 7e-16 and 3e-15), one pair summed at another cell's node moves its share N m_p by about h.
template <int D>
void expect_layer_moments(Solver<D>& s, const Scene& scene, double end) {
  const auto& P = s.particles;
  std::vector<Vec<D>> before = P.position;  // x^n of the step to come
  std::vector<int> cells(P.size(), -1), previous(P.size(), -1);
  int kept = 0, sorted = 0, checked = 0;
  double worst_mass = 0.0, worst_moment = 0.0;
  run_until(s, scene, end, [&](double, double) {
    const auto& w = s.dual_walls()[0];
    double mass = 0.0, node_mass = 0.0;
    Vec<D> moment = Vec<D>::Zero(), node_moment = Vec<D>::Zero();
    for (std::size_t p = 0; p < P.size(); ++p) {
      cells[p] = -1;
      if (P.layer_wall[p] < 0) continue;
      Eigen::Vector3d x = Eigen::Vector3d::Zero();
      x.template head<D>() = before[p];
      cells[p] = w.locator->locate(x).cell;
      mass += P.mass[p];
      moment += P.mass[p] * before[p];
    }
    for (std::size_t n = 0; n < w.mass.size(); ++n) {
      node_mass += w.mass[n];
      node_moment += w.mass[n] * w.position[n];
    }
    if (mass > 0.0) {
      ++checked;
      (cells == previous ? kept : sorted) += 1;
      // A pair summed at a node it does not have moves its mass by about a cell: scale m h.
      const double scale = mass * scene.spacing;
      worst_mass = std::max(worst_mass, std::abs(node_mass - mass) / mass);
      worst_moment = std::max(worst_moment, (node_moment - moment).norm() / scale);
    }
    previous = cells;
    before = P.position;
  });
  std::printf(
      "%dD: %d steps with layer particles, %d with the cells of the step before, %d not; "
      "mass error %.2e, moment error %.2e\n",
      D, checked, kept, sorted, worst_mass, worst_moment);
  EXPECT_GT(kept, checked / 4);
  EXPECT_GT(sorted, 1);
  EXPECT_LT(worst_mass, 1e-12);
  EXPECT_LT(worst_moment, 1e-12);
}

/// The incline's block moved `lift` along the wall's normal (its box's corners, so its centre).
void lift_block(InclineScene& in, int dimension, double lift) {
  for (auto& body : in.doc["bodies"]) {
    for (const char* bound : {"min", "max"}) {
      json& corner = body["shape"][bound];
      for (int i = 0; i < dimension; ++i) {
        const auto k = static_cast<std::size_t>(i);
        corner[k] = corner[k].get<double>() + lift * in.normal[i];
      }
    }
  }
}

TEST(LayerScatter, BoundaryGridHoldsItsParticlesMassAndMoment2D) {
  InclineScene in = incline_2d(20.0, 0.5, kInclineH, 0.5, "mortar");
  lift_block(in, 2, 0.02);
  const Scene scene = parse_scene(in.doc, "<settling block>");
  Solver<2> s(scene);
  expect_layer_moments(s, scene, 0.4);
}

// scheme.coupling_tolerance: the Phi coupling solves its multipliers until the grids'
// interface velocities agree to that fraction of their size. A block sliding down a mortar
// incline (a real interface force every step: its weight, carried across Phi); after every step
// the remapped velocities MUSL ends on satisfy R^A^T v^A = R^alpha^T v^alpha to the tolerance,
// momentum changes only by gravity and the wall, and a loose tolerance moves the block's path by
// no more than it allows.
struct CouplingRun {
  double worst_gap = 0.0;  ///< largest |R^A^T v^A - R^alpha^T v^alpha| / interface terms
  std::size_t passes = 0, factorizations = 0, steps = 0;
  Vec<2> centre = Vec<2>::Zero();
};

CouplingRun slide_with_tolerance(double tolerance, const std::string& method = "mortar",
                                 double theta = 36.0, double mu = 0.3) {
  InclineScene in = incline_2d(theta, mu, kInclineH, 0.5, method);
  in.doc["scheme"]["coupling_tolerance"] = tolerance;
  in.doc["time"]["end"] = 0.3;
  const Scene scene = parse_scene(in.doc, "<sliding block>");
  Solver<2> s(scene);
  CouplingRun r;
  run_until(s, scene, scene.end_time, [&](double, double) {
    const DualWall<2>& w = s.dual_walls()[0];
    ++r.steps;
    if (w.enhanced || w.grid_active.cols() == 0) return;
    Eigen::MatrixXd a(static_cast<Eigen::Index>(w.grid_rows.size()), 2);
    Eigen::MatrixXd b(static_cast<Eigen::Index>(w.layer_rows.size()), 2);
    for (Eigen::Index i = 0; i < a.rows(); ++i) {
      a.row(i) = s.grid.velocity[w.grid_rows[static_cast<std::size_t>(i)]].transpose();
    }
    for (Eigen::Index i = 0; i < b.rows(); ++i) {
      b.row(i) = w.velocity[static_cast<std::size_t>(w.layer_rows[static_cast<std::size_t>(i)])]
                     .transpose();
    }
    const Eigen::MatrixXd grid_terms = w.grid_active.transpose() * a;
    const Eigen::MatrixXd layer_terms = w.boundary_active.transpose() * b;
    const double scale = std::max(grid_terms.norm(), layer_terms.norm());
    r.worst_gap = std::max(r.worst_gap, (grid_terms - layer_terms).norm() / scale);
  });
  EXPECT_FALSE(s.fault().has_value()) << *s.fault();
  const DualWall<2>& w = s.dual_walls()[0];
  r.passes = w.enhanced ? w.enh.refinements : w.refinements;
  r.factorizations = w.enhanced ? w.enh.factorizations : w.factorizations;
  r.centre = centre_of_mass(s);
  return r;
}

TEST(PhiCoupling, InterfaceVelocitiesAgreeToTheSceneTolerance) {
  InclineScene start = incline_2d(36.0, 0.3, kInclineH, 0.5, "mortar");
  const Scene initial = parse_scene(start.doc, "<sliding block>");
  const Vec<2> x0 = centre_of_mass(Solver<2>(initial));
  const CouplingRun tight = slide_with_tolerance(1e-10);
  const double slid = (tight.centre - x0).norm();  // about 0.15 m: 3 cells
  std::size_t passes_before = tight.passes;
  for (const double tolerance : {1e-10, 1e-8, 1e-6, 1e-4}) {
    const CouplingRun r = tolerance == 1e-10 ? tight : slide_with_tolerance(tolerance);
    const double moved = (r.centre - tight.centre).norm();
    std::printf(
        "tolerance %.0e: %zu steps, largest gap %.3e of the interface terms, %zu passes, %zu "
        "factorisations, the block's centre %.3e h from the 1e-10 run's\n",
        tolerance, r.steps, r.worst_gap, r.passes, r.factorizations, moved / kInclineH);
    // CG stops on the gap before its last correction (measured against the terms before the
    // solve) or on a correction below the tolerance, which leaves about q of it: the gap after
    // the step is the tolerance to within the change of the terms (measured: 1.03-1.2 times).
    EXPECT_LE(r.worst_gap, 2.0 * tolerance) << tolerance;
    // Each step's velocities at Phi are off by at most that fraction, so the path by at most
    // that fraction of how far the block slid (measured: 1e-4 of that bound at 1e-6).
    EXPECT_LE(moved, tolerance * slid) << tolerance;
    EXPECT_LE(r.passes, passes_before) << tolerance;
    passes_before = r.passes;
  }
  // The default 1e-6 against 1e-10: 7,416 passes against 10,522 in this run.
  EXPECT_LT(passes_before, tight.passes);
}

// The Phi coupling in hand after every step is the one the step's masses give, assembled from
// scratch here: its multipliers those of the carried ones (a Phi node above the coupling
// threshold) whose supports hold mass on both grids, each column the nodes of its support above
// the threshold with R's entries rescaled to the multiplier's integral, bit for bit. A step
// whose carried multipliers and support nodes are on the same side of the threshold as when the
// coupling in hand was assembled keeps it without assembling (layer_couple()): a block resting
// on a level wall keeps it in nearly every step, one sliding down a 36 degree incline assembles
// it anew whenever the nodes under it change (51 of its 1,258 steps).
void expect_coupling_of_the_masses(double theta, double mu, double end, double kept_share,
                                   double multiplier_radius = 0.0) {
  InclineScene in = incline_2d(theta, mu, kInclineH, 0.5, "mortar");
  in.doc["time"]["end"] = end;
  in.doc["walls"][0]["multiplier_radius"] = multiplier_radius;
  const Scene scene = parse_scene(in.doc, "<block on a mortar wall>");
  Solver<2> s(scene);
  const double mean_mass = std::accumulate(s.particles.mass.begin(), s.particles.mass.end(), 0.0) /
                           static_cast<double>(s.particles.size());
  const double threshold =
      std::max(scene.mass_threshold, scene.coupling_mass_threshold) * mean_mass;
  std::size_t steps = 0, checked = 0;
  run_until(s, scene, scene.end_time, [&](double, double) {
    ++steps;
    const DualWall<2>& w = s.dual_walls()[0];
    std::vector<int> carried;
    for (std::size_t n = 0; n < w.mass.size(); ++n) {
      const int m = w.multiplier_of_node[n];
      if (m >= 0 && w.mass[n] > threshold) carried.push_back(m);
    }
    std::sort(carried.begin(), carried.end());
    carried.erase(std::unique(carried.begin(), carried.end()), carried.end());
    std::vector<int> active;
    // Per active multiplier, its (node, value) entries on either grid.
    std::vector<std::vector<std::pair<int, double>>> grid_columns, layer_columns;
    for (const int m : carried) {
      double grid_sum = 0.0, layer_sum = 0.0;
      for (Eigen::SparseMatrix<double>::InnerIterator it(w.grid_coupling, m); it; ++it) {
        if (s.grid.mass[it.row()] > threshold) grid_sum += it.value();
      }
      for (Eigen::SparseMatrix<double>::InnerIterator it(w.boundary_coupling, m); it; ++it) {
        if (w.mass[static_cast<std::size_t>(it.row())] > threshold) layer_sum += it.value();
      }
      if (grid_sum <= 1e-12 * w.multiplier_integral[m] || layer_sum <= 0.0) continue;
      active.push_back(m);
      auto& g = grid_columns.emplace_back();
      auto& l = layer_columns.emplace_back();
      const double gs = w.multiplier_integral[m] / grid_sum,
                   ls = w.multiplier_integral[m] / layer_sum;
      for (Eigen::SparseMatrix<double>::InnerIterator it(w.grid_coupling, m); it; ++it) {
        if (s.grid.mass[it.row()] > threshold) g.emplace_back(it.row(), gs * it.value());
      }
      for (Eigen::SparseMatrix<double>::InnerIterator it(w.boundary_coupling, m); it; ++it) {
        if (w.mass[static_cast<std::size_t>(it.row())] > threshold) {
          l.emplace_back(it.row(), ls * it.value());
        }
      }
    }
    ASSERT_EQ(w.active_multipliers, active) << "step " << steps;
    if (active.empty()) return;
    auto columns_of = [](const Eigen::SparseMatrix<double>& r, const std::vector<int>& rows) {
      std::vector<std::vector<std::pair<int, double>>> out(static_cast<std::size_t>(r.cols()));
      for (Eigen::Index c = 0; c < r.cols(); ++c) {
        for (Eigen::SparseMatrix<double>::InnerIterator it(r, c); it; ++it) {
          out[static_cast<std::size_t>(c)].emplace_back(rows[static_cast<std::size_t>(it.row())],
                                                        it.value());
        }
        std::sort(out[static_cast<std::size_t>(c)].begin(), out[static_cast<std::size_t>(c)].end());
      }
      return out;
    };
    for (auto& c : grid_columns) std::sort(c.begin(), c.end());
    for (auto& c : layer_columns) std::sort(c.begin(), c.end());
    ASSERT_EQ(columns_of(w.grid_active, w.grid_rows), grid_columns) << "step " << steps;
    ASSERT_EQ(columns_of(w.boundary_active, w.layer_rows), layer_columns) << "step " << steps;
    ++checked;
  });
  EXPECT_FALSE(s.fault().has_value()) << *s.fault();
  const DualWall<2>& w = s.dual_walls()[0];
  std::printf(
      "theta %.0f, multiplier radius %.0f: %zu steps, %zu with a coupling checked, %zu kept "
      "without assembling\n",
      theta, multiplier_radius, steps, checked, w.kept_assemblies);
  EXPECT_GT(checked, steps / 2);
  EXPECT_GE(static_cast<double>(w.kept_assemblies), kept_share * static_cast<double>(steps));
}

TEST(PhiCoupling, TheCouplingInHandIsTheOneTheStepsMassesGive) {
  expect_coupling_of_the_masses(0.0, 0.3, 0.3, 0.5);   // resting: kept in most steps
  expect_coupling_of_the_masses(36.0, 0.3, 0.3, 0.0);  // sliding: assembled when it changes
  // Merged multipliers: one is carried while any of its Phi nodes is, so its support's nodes
  // on Phi can leave while it stays.
  expect_coupling_of_the_masses(36.0, 0.3, 0.3, 0.0, 1.0);
}

// Enhanced solves its contact system to the same tolerance, its impulse unknowns measured as
// the velocities they give the standard grid (enhanced_solve()). A block resting on a 20 degree
// incline (mu 0.5: it sticks and settles), where the contact holds from step to step and the
// solves refine against an earlier factorisation (sliding, every active-set pass factorises
// anew and the tolerance never enters).
TEST(EnhancedCoupling, ContactSystemSolvedToTheSceneTolerance) {
  InclineScene start = incline_2d(20.0, 0.5, kInclineH, 0.5, "enhanced");
  const Scene initial = parse_scene(start.doc, "<resting block>");
  const Vec<2> x0 = centre_of_mass(Solver<2>(initial));
  const CouplingRun tight = slide_with_tolerance(1e-10, "enhanced", 20.0, 0.5);
  const double slid = (tight.centre - x0).norm();  // its settling
  std::printf("the block settles by %.3e h\n", slid / kInclineH);
  std::size_t passes_before = tight.passes;
  for (const double tolerance : {1e-10, 1e-8, 1e-6, 1e-4}) {
    const CouplingRun r =
        tolerance == 1e-10 ? tight : slide_with_tolerance(tolerance, "enhanced", 20.0, 0.5);
    const double moved = (r.centre - tight.centre).norm();
    std::printf(
        "tolerance %.0e: %zu steps, %zu passes, %zu factorisations, the block's centre %.3e h "
        "from the 1e-10 run's\n",
        tolerance, r.steps, r.passes, r.factorizations, moved / kInclineH);
    // Each step's velocities are off by at most the tolerance of their size (the impulses
    // counted as the velocities they make), so the path by at most that fraction of how far
    // the block moved.
    EXPECT_LE(moved, tolerance * slid) << tolerance;
    EXPECT_LE(r.passes, passes_before) << tolerance;
    passes_before = r.passes;
  }
  EXPECT_LT(passes_before, tight.passes);
}

TEST(LayerScatter, BoundaryGridHoldsItsParticlesMassAndMoment3D) {
  const TempDir dir;
  InclineScene in = incline_3d(20.0, 0.5, dir.path(), "mortar");
  lift_block(in, 3, 0.02);
  const Scene scene = parse_scene(in.doc, "<settling block>");
  Solver<3> s(scene);
  expect_layer_moments(s, scene, 0.25);
}

// Sweeps in both dual-grid forms: Blending (mortar, with one multiplier per Phi node and with
// them merged within h) and Enhanced, the same tolerances.
INSTANTIATE_TEST_SUITE_P(MethodAndFriction, BlendingIncline,
                         ::testing::Combine(::testing::Values("mortar", "mortar_coarse",
                                                              "enhanced"),
                                            ::testing::Values(0.0, 0.3)),
                         [](const auto& p) {
                           return std::string(std::get<0>(p.param)) +
                                  (std::get<1>(p.param) > 0.0 ? "Mu03" : "Mu0");
                         });

// The mortar incline under USL and MLS-MPM (and USL with PIC), segments of h at CFL 0.4: their
// layer particles take the strain rate from v^{n+1}. Before nodes below the coupling threshold
// were left out of it (layer_gather()) the block diverged within 0.2 s at every angle, under
// APIC, FLIP and PIC alike; before the layer's cell counted half in the time step for them too,
// PIC and FLIP still did. Same bounds as the MUSL sweeps.
class BlendingInclineUpdate
    : public ::testing::TestWithParam<std::tuple<const char*, const char*, double>> {};

TEST_P(BlendingInclineUpdate, AngleInvariance2DSegmentsOfHAtCfl04) {
  const auto [update, transfer, mu] = GetParam();
  std::vector<InclineResult> results;
  for (double theta : kInclineAngles) {
    InclineScene in = incline_2d(theta, mu, kInclineH, 0.4, "mortar");
    in.doc["scheme"] = {{"update", update}, {"transfer", transfer}};
    results.push_back(run_incline<2>(in, theta, mu));
  }
  check_incline_sweep(std::string("mortar ") + update + "/" + transfer, mu, results);
}

INSTANTIATE_TEST_SUITE_P(UpdateAndFriction, BlendingInclineUpdate,
                         ::testing::Combine(::testing::Values("usl", "mls"),
                                            ::testing::Values("apic"), ::testing::Values(0.0, 0.3)),
                         [](const auto& p) {
                           return std::string(std::get<0>(p.param)) +
                                  (std::get<2>(p.param) > 0.0 ? "Mu03" : "Mu0");
                         });
INSTANTIATE_TEST_SUITE_P(UslPic, BlendingInclineUpdate,
                         ::testing::Values(std::make_tuple("usl", "pic", 0.3)),
                         [](const auto&) { return std::string("uslPicMu03"); });

// One mesh, two parts with different conditions (a terrain and the barrier on it): the incline
// of the sweeps at 43 degrees cut across at u = 0.5 m into "upper" (where the block slides, it
// reaches u = 0.35 m) and "lower". The wall's own condition is one coefficient and the upper
// part's (the scene's "parts") the other, both ways round: the block must follow the upper
// part's exact answer (d = a T^2 / 2, a = g (sin - mu cos), the friction force mu N), and the
// lower part, which the block never reaches, must report no force. With the wall's condition
// used everywhere instead, d would be off by the ratio of the two accelerations (2.0 here).
class PartConditions : public ::testing::TestWithParam<std::tuple<const char*, bool>> {};

TEST_P(PartConditions, EachPartTakesItsOwnCondition) {
  const auto [method, friction_on_part] = GetParam();
  const double theta = 43.0, mu = 0.3;
  const double mu_part = friction_on_part ? mu : 0.0, mu_wall = friction_on_part ? 0.0 : mu;
  const TempDir dir;
  InclineScene in = incline_3d(theta, mu_wall, dir.path(), method, 0.5);
  in.doc["walls"][0]["parts"] = {{"upper", contact_json(mu_part)}};
  in.doc["walls"][0]["parts"]["upper"].erase("separable");
  const Scene scene = parse_scene(in.doc, "<parts>");
  const auto& names = scene.dual_walls[0].package->layer.part_names;
  ASSERT_EQ(names, (std::vector<std::string>{"upper", "lower"}));
  const InclineResult r = run_incline<3>(in, theta, mu_part);
  std::printf(
      "%s, mu %.1f on the upper part (%.1f on the wall): d/d_exact %.5f F_n/(mg cos) %.4f "
      "F_t/(mu mg cos) %.4f |v_n|max/(gT) %.2e\n",
      method, mu_part, mu_wall, r.displacement, r.normal_force, r.friction_force, r.normal_speed);
  // The sweeps' tolerances (check_incline_sweep).
  EXPECT_NEAR(r.displacement, 1.0, 0.03);
  EXPECT_NEAR(r.normal_force, 1.0, 0.03);
  if (mu_part > 0.0) {
    EXPECT_NEAR(r.friction_force, 1.0, 0.03);
  }
  EXPECT_LT(r.normal_speed, 0.01);
  // Separable: a Gamma node of the lower part acts only once a particle lies over its share of
  // the wall, and none gets within a cell of it.
  EXPECT_EQ(r.other_parts, 0.0);
}

INSTANTIATE_TEST_SUITE_P(MethodAndPart, PartConditions,
                         ::testing::Combine(::testing::Values("mortar", "enhanced"),
                                            ::testing::Bool()),
                         [](const auto& p) {
                           return std::string(std::get<0>(p.param)) +
                                  (std::get<1>(p.param) ? "FrictionOnPart" : "SlipOnPart");
                         });

// A block at rest on a 20 degree incline with mu = 0.5 > tan 20 sticks: exact answer, no motion,
// and with nothing but friction and the transfers acting, the energy can only fall. Run at
// CFL 0.5 for 12.5k steps (3 s), bonded and separable. Enhanced used to re-apply the step's
// friction loads in the MUSL remap: the strain rate took each sliding node's friction twice,
// the block crushed itself and gained energy (bonded: runaway near step 14.5k; separable: 0.58 h
// of creep and 29% energy growth in `mpm bench stability`'s 10^5-step run).
class RestingBlock : public ::testing::TestWithParam<std::tuple<const char*, bool>> {};

TEST_P(RestingBlock, SticksAndNeverGainsEnergy) {
  const auto [method, separable] = GetParam();
  InclineScene in = incline_2d(20.0, 0.5, kInclineH, 0.5, method);
  in.doc["walls"][0]["separable"] = separable;
  in.doc["time"]["end"] = 3.0;
  const Scene scene = parse_scene(in.doc, "<resting block>");
  Solver<2> s(scene);
  const double mass = total_mass(s);
  const Vec<2> x0 = centre_of_mass(s);
  const double e0 = s.energies().total();
  double growth = 0.0;
  std::size_t steps = 0;
  run_until(s, scene, scene.end_time, [&](double, double) {
    growth = std::max(growth, s.energies().total() - e0);
    ++steps;
  });
  ASSERT_FALSE(s.fault().has_value()) << *s.fault();
  const double creep = std::abs((centre_of_mass(s) - x0).dot(in.downhill.head<2>())) / kInclineH;
  // Scale: the block's weight times its height (0.15 m), 66 J. A separable wall may lift the
  // block once as it settles onto its touch distance (mortar: 3.6e-4 of the scale, reached in
  // the first second and flat after); the bound is 1e-3, which the double friction crossed within
  // 3000 steps. The creep bound is 1% of a cell over 3 s (measured: 0.2-0.45%, the elastic
  // settling on a sticking contact).
  const double scale = mass * kGravity * 0.15;
  std::printf("%s %s: %zu steps, energy growth %.3e of m g b, creep %.3e h\n", method,
              separable ? "separable" : "bonded", steps, growth / scale, creep);
  EXPECT_LE(growth, 1e-3 * scale);
  EXPECT_LT(creep, 0.01);
}

INSTANTIATE_TEST_SUITE_P(MethodAndSeparation, RestingBlock,
                         ::testing::Combine(::testing::Values("mortar", "enhanced"),
                                            ::testing::Bool()),
                         [](const auto& p) {
                           return std::string(std::get<0>(p.param)) +
                                  (std::get<1>(p.param) ? "Separable" : "Bonded");
                         });

// A granular stream at 4 m/s along a rough floor into the foot of a wall, floor and wall one
// polyline (the concave corner of a barrier on the ground). The Gamma node at the foot has two
// facets; with only its own normal (their bisector) acting ("corners": "normal", the default
// until 2026-12-03), the stream's front particle slides along the bisector's tangent into the
// wall and leaves through the corner (here 4.05 h behind the wall by 0.4 s; the run faults at
// step ~5000 at 3 m/s, ~7500 at 4 m/s, in the impact study of docs/validation.md). Mortar runs
// with its default, "corners": "facets" (the foot held against both); Enhanced holds Gamma
// through its contact multipliers and has no such option. Checked every step: no particle
// centre behind the floor or the wall by more than kBehindTolerance h, the mass kept, and
// the horizontal momentum changed only by the wall's impulse (gravity is vertical; the
// coupling's impulses across Phi cancel).
class CornerImpact : public ::testing::TestWithParam<const char*> {};

TEST_P(CornerImpact, NothingLeavesThroughTheFootOfAWall) {
  const std::string method = GetParam();
  constexpr double h = 0.0125, wall_x = 0.6, v0 = 4.0;
  json wall = contact_json(0.4);
  wall["name"] = "barrier";
  set_method(wall, method);
  wall["surface"] = {{"type", "polyline"}, {"points", {{0.0, 0.0}, {wall_x, 0.0}, {wall_x, 1.2}}}};
  const json doc = {
      {"name", "corner_impact"},
      {"dimension", 2},
      {"grid", {{"min", {-4 * h, -4 * h}}, {"max", {wall_x + 4 * h, 1.25}}, {"spacing", h}}},
      {"shape_function", "bspline2"},
      {"scheme", {{"update", "musl"}, {"transfer", "apic"}}},
      {"gravity", {0.0, -kGravity}},
      {"materials",
       {{{"name", "debris"},
         {"model", "drucker_prager"},
         {"density", 1800.0},
         {"youngs_modulus", 5.0e6},
         {"poisson_ratio", 0.3},
         {"friction_angle", 30.0},
         {"dilatancy_angle", 0.0},
         {"cohesion", 0.0}}}},
      {"bodies",
       {{{"name", "flow"},
         {"material", "debris"},
         {"particles_per_cell", 2},
         {"velocity", {v0, 0.0}},
         {"shape", {{"type", "box"}, {"min", {0.1, 0.0}}, {"max", {wall_x - 0.05, 0.1}}}}}}},
      {"walls", json::array({wall})},
      {"time", {{"end", 0.4}, {"cfl", 0.5}}}};
  const Scene scene = parse_scene(doc, "<corner impact>");
  // The corner rule is the Blending walls' default (the scene does not ask for it).
  ASSERT_EQ(scene.dual_walls.at(0).corner_facets, method == "mortar");
  Solver<2> s(scene);
  const double mass = total_mass(s);
  const double px0 = s.momentum()[0];
  double impulse_x = 0.0, behind = -std::numeric_limits<double>::infinity(), balance = 0.0;
  std::size_t steps = 0;
  run_until(s, scene, scene.end_time, [&](double, double) {
    for (const auto& x : s.particles.position) behind = std::max({behind, -x[1], x[0] - wall_x});
    for (const auto& impulse : s.wall_impulses()) impulse_x += impulse[0];
    s.reset_wall_impulses();
    balance = std::max(balance, std::abs(s.momentum()[0] - px0 - impulse_x) / (mass * v0));
    ++steps;
  });
  std::printf(
      "%s: %zu steps, deepest particle centre %.3e h behind the floor or the wall, "
      "x-momentum balance %.2e of m v0\n",
      method.c_str(), steps, behind / h, balance);
  EXPECT_LE(behind, kBehindTolerance * h);
  EXPECT_EQ(total_mass(s), mass);
  // Mortar's impulses across Phi cancel to round-off (its free flight: 1e-10), so the wall's
  // recorded impulse is the whole change; Enhanced's recorded contact impulses are the whole
  // change too (measured 1.2e-10 and 1.2e-11 of m v0 on 2026-12-06; Enhanced's was noted at
  // ~1e-5 when this test was written and left unchecked; which later change closed it was not
  // traced).
  EXPECT_LT(balance, 1e-9);
}

INSTANTIATE_TEST_SUITE_P(Methods, CornerImpact, ::testing::Values("mortar", "enhanced"),
                         [](const auto& p) { return std::string(p.param); });

// A layer particle's stress is updated after the standard grid's pass (update_layer_stress):
// invert one the boundary layer holds and the step names it, under both methods (Blending's
// layer owns the particle; Enhanced's completes its gradient).
class LayerStepCheck : public ::testing::TestWithParam<const char*> {};

TEST_P(LayerStepCheck, NamesAnInvertedLayerParticle) {
  InclineScene in = incline_2d(20.0, 0.5, kInclineH, 0.5, GetParam());
  const Scene scene = parse_scene(in.doc, "<layer step check>");
  Solver<2> s(scene);
  const double dt = s.stable_dt(0.5);
  s.step(dt);
  ASSERT_FALSE(s.fault().has_value()) << *s.fault();
  const auto& walls = s.particles.layer_wall;
  const auto in_layer = std::ranges::find_if(walls, [](int w) { return w >= 0; });
  ASSERT_NE(in_layer, walls.end()) << "no particle in the boundary layer";
  const auto held = static_cast<std::size_t>(in_layer - walls.begin());
  // The incline's block is Neo-Hookean: with F inverted its stress turns non-finite (log J), so
  // the step may report either condition, but must name this particle.
  s.particles.deformation_gradient[held](0, 0) *= -1.0;
  s.step(dt);
  ASSERT_TRUE(s.fault().has_value());
  const std::string& fault = *s.fault();
  EXPECT_NE(fault.find("particle " + std::to_string(held) + " "), std::string::npos) << fault;
  EXPECT_TRUE(fault.find("deformation gradient inverted") != std::string::npos ||
              fault.find("stress is not finite") != std::string::npos)
      << fault;
}

INSTANTIATE_TEST_SUITE_P(Methods, LayerStepCheck, ::testing::Values("mortar", "enhanced"),
                         [](const auto& p) { return std::string(p.param); });

// A dual-grid coupling runs on one core beside the gather of the particles it cannot change
// (Solver::couple_beside()): those the step takes as free must be in no layer, and every node
// of their stencils outside the standard-grid nodes the coupling may write (Blending: every row
// of R^A; Enhanced: the rows of the step's contact system). The tilted incline's wall crosses
// cells at every offset; each method and kernel, 2D and 3D.
class CouplingOverlap : public ::testing::TestWithParam<std::tuple<const char*, const char*>> {};

// Moves a body of the incline scene (a box) `lift` along the incline's normal.
template <int D>
void lift_block(const InclineScene& in, json& block, double lift) {
  for (const char* key : {"min", "max"}) {
    for (int d = 0; d < D; ++d)
      block["shape"][key][d] = block["shape"][key][d].get<double>() + lift * in.normal[d];
  }
}

// Adds a copy of the incline's block `lift` along the normal, named "upper" (falling freely
// above the block: its particles reach no coupled node).
template <int D>
void add_lifted_block(InclineScene& in, double lift) {
  json upper = in.doc["bodies"][0];
  upper["name"] = "upper";
  lift_block<D>(in, upper, lift);
  in.doc["bodies"].push_back(upper);
}

// The incline's block (3 cells thick: every particle reaches the coupled nodes) and a copy of
// it `lift` along the normal, falling freely above it, whose particles do not.
template <int D>
void expect_free_particles_untouched(InclineScene in, double lift) {
  add_lifted_block<D>(in, lift);
  const Scene scene = parse_scene(in.doc, "<coupling overlap>");
  Solver<D> s(scene);
  const double dt = s.stable_dt(0.5);
  for (int step = 0; step < 3; ++step) s.step(dt);
  ASSERT_FALSE(s.fault().has_value()) << *s.fault();
  // Blending: every row of R^A (a superset of what the step writes); Enhanced: the rows the
  // step's contact system has (those it writes).
  std::vector<char> written(s.grid.size(), 0);
  for (const DualWall<D>& w : s.dual_walls()) {
    if (w.enhanced) {
      for (const int node : w.enh.a_rows) written[static_cast<std::size_t>(node)] = 1;
      continue;
    }
    for (Eigen::Index col = 0; col < w.grid_coupling.outerSize(); ++col) {
      for (Eigen::SparseMatrix<double>::InnerIterator it(w.grid_coupling, col); it; ++it) {
        written[static_cast<std::size_t>(it.row())] = 1;
      }
    }
  }
  const auto& near = s.near_coupling();
  ASSERT_EQ(near.size(), s.particles.size());
  std::size_t free = 0, reaching = 0;  // free particles; particles reaching a written node
  dispatch_shape(scene.shape, [&](auto shape) {
    for (std::size_t p = 0; p < s.particles.size(); ++p) {
      const Stencil<D, decltype(shape)> st(s.grid, s.particles.position[p],
                                           s.particles.half_width[p]);
      bool reaches = false;
      st.for_each(s.grid, [&](int node, double, const Vec<D>&, const Vec<D>&) {
        reaches = reaches || written[static_cast<std::size_t>(node)] != 0;
      });
      reaching += reaches ? 1 : 0;
      if (near[p] != 0) continue;
      ++free;
      EXPECT_FALSE(reaches) << "free particle " << p << " reaches a node the coupling writes";
      EXPECT_LT(s.particles.layer_wall[p], 0) << "free particle " << p << " is in the layer";
    }
  });
  // Not vacuous: both kinds are there, and the cell test takes most of the others as free.
  EXPECT_GT(reaching, 0U);
  EXPECT_GT(free, 0U);
  EXPECT_LE(s.particles.size() - free, 2 * reaching)
      << "free " << free << " of " << s.particles.size();
  std::printf("%zu particles: %zu free, %zu reach a node the coupling writes\n", s.particles.size(),
              free, reaching);
}

TEST_P(CouplingOverlap, FreeParticlesReachNoNodeTheCouplingWrites2D) {
  const auto& [method, shape] = GetParam();
  InclineScene in = incline_2d(20.0, 0.5, kInclineH, 0.5, method);
  in.doc["shape_function"] = shape;
  expect_free_particles_untouched<2>(in, 0.25);
}

TEST_P(CouplingOverlap, FreeParticlesReachNoNodeTheCouplingWrites3D) {
  const auto& [method, shape] = GetParam();
  TempDir dir;
  InclineScene in = incline_3d(20.0, 0.5, dir.path(), method);
  in.doc["shape_function"] = shape;
  expect_free_particles_untouched<3>(in, 0.2);
}

INSTANTIATE_TEST_SUITE_P(MethodAndShape, CouplingOverlap,
                         ::testing::Combine(::testing::Values("mortar", "one-way", "enhanced"),
                                            ::testing::Values("bspline2", "gimp", "linear")),
                         method_and_shape_name);

// The coupling beside the free particles' gather or before one gather of all (the step picks the
// way that has lately been faster, Solver::couple_beside()): the same particles bit for bit, and
// the adaptive choice runs both. The incline's block and a copy falling freely above it (free
// particles), under MUSL (two couplings a step) and MLS-MPM.
class CouplingOverlapWays : public ::testing::TestWithParam<std::tuple<const char*, const char*>> {
};

template <int D>
void expect_overlap_ways_agree(InclineScene in, double lift, const char* update, int threads = 0) {
  add_lifted_block<D>(in, lift);
  in.doc["scheme"]["update"] = update;
  const Scene scene = parse_scene(in.doc, "<coupling overlap ways>");
  // One thread: the coupling task and the free pass on the same thread, in whatever order TBB
  // takes them.
  std::optional<tbb::global_control> limit;
  if (threads > 0) limit.emplace(tbb::global_control::max_allowed_parallelism, threads);
  using Way = typename Solver<D>::CouplingOverlap;
  std::vector<std::unique_ptr<Solver<D>>> runs;
  for (const Way way : {Way::after, Way::beside, Way::adaptive}) {
    runs.push_back(std::make_unique<Solver<D>>(scene));
    runs.back()->set_coupling_overlap(way);
  }
  const double dt = runs[0]->stable_dt(0.5);
  for (int step = 0; step < 6; ++step) {
    for (auto& s : runs) s->step(dt);
  }
  for (auto& s : runs) ASSERT_FALSE(s->fault().has_value()) << *s->fault();
  const std::size_t layer = runs[0]->dual_walls()[0].layer_particles;
  EXPECT_GT(layer, 0U) << "no particle in the layer: nothing coupled";
  const Particles<D>& a = runs[0]->particles;
  for (std::size_t r = 1; r < runs.size(); ++r) {
    const Particles<D>& b = runs[r]->particles;
    for (std::size_t p = 0; p < a.size(); ++p) {
      ASSERT_EQ(a.position[p], b.position[p]) << "run " << r << ", particle " << p;
      ASSERT_EQ(a.velocity[p], b.velocity[p]) << "run " << r << ", particle " << p;
      ASSERT_EQ(a.affine[p], b.affine[p]) << "run " << r << ", particle " << p;
      ASSERT_EQ(a.deformation_gradient[p], b.deformation_gradient[p])
          << "run " << r << ", particle " << p;
      ASSERT_EQ(a.stress[p], b.stress[p]) << "run " << r << ", particle " << p;
    }
  }
  const auto forced_after = runs[0]->coupling_overlap_counts();
  const auto forced_beside = runs[1]->coupling_overlap_counts();
  const auto adaptive = runs[2]->coupling_overlap_counts();
  EXPECT_EQ(forced_after[1], 0U);
  EXPECT_EQ(forced_beside[0], 0U);
  EXPECT_GE(adaptive[0], 2U);  // each way measured at least twice
  EXPECT_GE(adaptive[1], 2U);
}

TEST_P(CouplingOverlapWays, SameParticlesBitForBit2D) {
  const auto& [method, update] = GetParam();
  expect_overlap_ways_agree<2>(incline_2d(20.0, 0.5, kInclineH, 0.5, method), 0.25, update);
}

TEST_P(CouplingOverlapWays, SameParticlesBitForBit2DOneThread) {
  const auto& [method, update] = GetParam();
  expect_overlap_ways_agree<2>(incline_2d(20.0, 0.5, kInclineH, 0.5, method), 0.25, update, 1);
}

TEST_P(CouplingOverlapWays, SameParticlesBitForBit3D) {
  const auto& [method, update] = GetParam();
  TempDir dir;
  expect_overlap_ways_agree<3>(incline_3d(20.0, 0.5, dir.path(), method), 0.2, update);
}

INSTANTIATE_TEST_SUITE_P(MethodAndUpdate, CouplingOverlapWays,
                         ::testing::Combine(::testing::Values("mortar", "enhanced"),
                                            ::testing::Values("musl", "mls")),
                         method_and_shape_name);

// locate_in_layers() skips the particles that cannot have reached a layer's or a coupling's
// cells since it last looked at them (their travel less than their distance from those cells
// then): the same layer particles and near-coupling flags every step, and the same particles bit
// for bit, as looking at every particle every step. The incline's block lifted `lift` along the
// normal and thrown at the incline: its particles start far from the layer (skipped) and cross
// cells into it within the run, so a skipped particle must be looked at again in time.
template <int D>
void expect_locate_skipping_exact(InclineScene in, double lift, double speed, int steps) {
  json& block = in.doc["bodies"][0];
  lift_block<D>(in, block, lift);
  block["velocity"] = json::array();
  for (int d = 0; d < D; ++d) block["velocity"].push_back(-speed * in.normal[d]);
  const Scene scene = parse_scene(in.doc, "<locate skipping>");
  Solver<D> skipping(scene), every(scene);
  every.set_locate_skipping(false);
  const double dt = skipping.stable_dt(0.5);
  std::size_t most_in_layer = 0;
  int step = 0;
  for (int after = 0; step < 2000 && after < steps; ++step) {  // `steps` once in the layer
    skipping.step(dt);
    every.step(dt);
    ASSERT_FALSE(skipping.fault().has_value()) << *skipping.fault();
    ASSERT_FALSE(every.fault().has_value()) << *every.fault();
    const Particles<D>& a = skipping.particles;
    const Particles<D>& b = every.particles;
    for (std::size_t p = 0; p < a.size(); ++p) {
      ASSERT_EQ(a.layer_wall[p], b.layer_wall[p]) << "step " << step << ", particle " << p;
      ASSERT_EQ(skipping.near_coupling()[p], every.near_coupling()[p])
          << "step " << step << ", particle " << p;
    }
    most_in_layer = std::max(most_in_layer, skipping.dual_walls()[0].layer_particles);
    if (most_in_layer > 0) ++after;
  }
  const Particles<D>& a = skipping.particles;
  const Particles<D>& b = every.particles;
  for (std::size_t p = 0; p < a.size(); ++p) {
    ASSERT_EQ(a.position[p], b.position[p]) << "particle " << p;
    ASSERT_EQ(a.velocity[p], b.velocity[p]) << "particle " << p;
    ASSERT_EQ(a.stress[p], b.stress[p]) << "particle " << p;
  }
  // Not vacuous: particles were skipped, and the block reached the layer.
  EXPECT_GT(skipping.locate_skipped(), 0U);
  EXPECT_EQ(every.locate_skipped(), 0U);
  EXPECT_GT(most_in_layer, 0U) << "the block never reached the layer";
  std::printf("%zu particles x %d steps: %zu skipped, at most %zu in the layer\n", a.size(), step,
              skipping.locate_skipped(), most_in_layer);
}

class LocateSkipping : public ::testing::TestWithParam<const char*> {};

TEST_P(LocateSkipping, SameLayerAndParticlesAsLookingAtAll2D) {
  expect_locate_skipping_exact<2>(incline_2d(20.0, 0.5, kInclineH, 0.5, GetParam()), 0.4, 4.0, 30);
}

TEST_P(LocateSkipping, SameLayerAndParticlesAsLookingAtAll3D) {
  TempDir dir;
  expect_locate_skipping_exact<3>(incline_3d(20.0, 0.5, dir.path(), GetParam()), 0.3, 4.0, 30);
}

INSTANTIATE_TEST_SUITE_P(Method, LocateSkipping, ::testing::Values("mortar", "one-way", "enhanced"),
                         method_name);

// The Phi coupling's products with R^A and R^alpha run on both cores, each row of a product
// summed by one task in the order Eigen's products sum it (layer_couple()): one thread and two
// give the same particles bit for bit. The floor benchmark's block resting on a floor mesh 0.3 h
// off the grid lines (bench/perf_scenes.hpp, 20 cells a side: 809 multipliers, so that the
// products' rows and columns split into several tasks); the first step factorises, the later
// ones refine against that factor (the conjugate gradients' products).
class PhiCouplingThreads : public ::testing::TestWithParam<std::tuple<const char*, const char*>> {};

TEST_P(PhiCouplingThreads, SameParticlesOnOneAndTwoThreads) {
  const auto& [method, update] = GetParam();
  const Scene scene = perf::floor_scene(20, std::string(method) == "mortar" ? 1 : 2, update);
  std::vector<std::unique_ptr<Solver<3>>> runs;
  for (const int threads : {1, 2}) {
    const tbb::global_control limit(tbb::global_control::max_allowed_parallelism, threads);
    runs.push_back(std::make_unique<Solver<3>>(scene));
    const double dt = runs.back()->stable_dt(0.4);
    for (int step = 0; step < 12; ++step) runs.back()->step(dt);
    ASSERT_FALSE(runs.back()->fault().has_value()) << *runs.back()->fault();
  }
  const std::vector<CouplingWork> work = runs[0]->coupling_work();
  ASSERT_EQ(work.size(), 1U);
  EXPECT_GT(work[0].multipliers, 256U);  // more than one task's columns
  EXPECT_GT(work[0].refinement_passes, 0U) << "no step refined: the products were not used";
  std::printf("%zu particles, %zu multipliers, %zu factorisations, %zu refinement passes\n",
              runs[0]->particles.size(), work[0].multipliers, work[0].factorizations,
              work[0].refinement_passes);
  const Particles<3>& a = runs[0]->particles;
  const Particles<3>& b = runs[1]->particles;
  for (std::size_t p = 0; p < a.size(); ++p) {
    ASSERT_EQ(a.position[p], b.position[p]) << "particle " << p;
    ASSERT_EQ(a.velocity[p], b.velocity[p]) << "particle " << p;
    ASSERT_EQ(a.affine[p], b.affine[p]) << "particle " << p;
    ASSERT_EQ(a.stress[p], b.stress[p]) << "particle " << p;
  }
}

INSTANTIATE_TEST_SUITE_P(MethodAndUpdate, PhiCouplingThreads,
                         ::testing::Combine(::testing::Values("mortar", "one-way"),
                                            ::testing::Values("musl", "mls")),
                         method_and_shape_name);

}  // namespace
}  // namespace mpm
