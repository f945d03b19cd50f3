#pragma once
// The main scene (data/scenes/debris_wall.json) for the tests that turn it against the grid: run
// it and read what summary.json says of the barrier and the flow, and turn it by a rotation
// (terrain, barrier, source and gravity together).

#include <unistd.h>

#include <Eigen/Geometry>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <numbers>
#include <string>

#include <gtest/gtest.h>
#include <nlohmann/json.hpp>

#include "mpm/run.hpp"
#include "mpm/scene.hpp"

namespace mpm::test {

inline const std::filesystem::path kDebrisScene =
    std::filesystem::path(MPM_DATA_DIR) / "scenes" / "debris_wall.json";

/// What the rotation tests compare, from a run's summary.json.
struct DebrisOutcome {
  double peak_force = 0.0, peak_time = 0.0, impulse = 0.0, runout = 0.0, runout_deep = 0.0,
         mass_change = 1.0, retained = 0.0;
  NLOHMANN_DEFINE_TYPE_INTRUSIVE(DebrisOutcome, peak_force, peak_time, impulse, runout, runout_deep,
                                 mass_change, retained)
};

/// The shipped scene with its output cut to the end of the run and its boundary-grid cache left
/// alone (the user's), at `spacing` (0: the shipped one).
inline nlohmann::json shipped_debris_scene(double spacing = 0.0) {
  std::ifstream in(kDebrisScene);
  nlohmann::json doc = nlohmann::json::parse(in);
  if (spacing > 0.0) doc["grid"]["spacing"] = spacing;
  doc["output"]["interval"] = doc["time"]["end"];
  for (auto& wall : doc["walls"]) {
    if (wall.contains("surface")) wall["surface"].erase("cache");
  }
  return doc;
}

/// Runs `doc` (read as if it were the shipped scene's file) and returns what its summary says.
inline DebrisOutcome run_debris(const nlohmann::json& doc, const std::string& label) {
  namespace fs = std::filesystem;
  // The pid in the name: two build trees (release and sanitizer) may run this test at once.
  const fs::path out =
      fs::temp_directory_path() / ("mpm_test_debris_" + label + "_" + std::to_string(::getpid()));
  const mpm::Scene scene = mpm::parse_scene(doc, kDebrisScene);
  mpm::RunOptions options;
  options.out_dir = out;
  options.overwrite = true;
  options.quiet = true;
  EXPECT_EQ(mpm::run_scene(scene, options), 0) << label;
  std::ifstream in(out / "summary.json");
  const nlohmann::json summary = nlohmann::json::parse(in);
  const nlohmann::json& barrier = summary["walls"]["slope_barrier"];
  const nlohmann::json& flow = summary["flow"];
  DebrisOutcome o;
  o.peak_force = barrier["peak_force"].get<double>();
  o.peak_time = barrier["peak_force_time"].get<double>();
  o.impulse = barrier["impulse"].get<double>();
  o.runout = flow["runout_distance"].get<double>();
  // The first of the scene's runout_depths (the shipped scene's: 0.5 m).
  o.runout_deep = flow["runout_at_depth"][0]["distance"].get<double>();
  o.mass_change = flow["mass_relative_change"].get<double>();
  o.retained = flow["retaining_walls"]["slope_barrier"]["volume_on_source_side"].get<double>();
  std::printf(
      "%s: peak barrier force %.4g N at %.3f s, barrier impulse %.4g N s, run-out %.4g m "
      "(%.4g m where the deposit is %g m deep), retained %.4g m^3\n",
      label.c_str(), o.peak_force, o.peak_time, o.impulse, o.runout, o.runout_deep,
      flow["runout_at_depth"][0]["depth"].get<double>(), o.retained);
  fs::remove_all(out);
  return o;
}

/// The bar for turned scene `b` (rotation `k`) against the scene as shipped, `a`: the
/// same peak force (within `peak_tolerance`) and run-out within 5%, and the barrier's impulse,
/// the momentum the flow brings it; mass exact in both (the particles carry it).
inline void expect_turned_outcome_agrees(const DebrisOutcome& a, const DebrisOutcome& b, int k,
                                         double peak_tolerance = 0.05) {
  EXPECT_NEAR(a.mass_change, 0.0, 1e-12);
  EXPECT_NEAR(b.mass_change, 0.0, 1e-12);
  EXPECT_GT(a.peak_force, 0.0);  // the flow reaches the barrier and loads it
  EXPECT_NEAR(b.peak_force / a.peak_force, 1.0, peak_tolerance) << "rotation " << k;
  EXPECT_NEAR(b.runout / a.runout, 1.0, 0.05) << "rotation " << k;
  EXPECT_NEAR(b.runout_deep / a.runout_deep, 1.0, 0.05) << "rotation " << k;
  EXPECT_NEAR(b.impulse / a.impulse, 1.0, 0.05) << "rotation " << k;
  const std::string tag = "rotation" + std::to_string(k) + "_";
  ::testing::Test::RecordProperty(tag + "peak_force_ratio",
                                  std::to_string(b.peak_force / a.peak_force));
  ::testing::Test::RecordProperty(tag + "impulse_ratio", std::to_string(b.impulse / a.impulse));
  ::testing::Test::RecordProperty(tag + "runout_ratio", std::to_string(b.runout / a.runout));
  ::testing::Test::RecordProperty(tag + "runout_at_depth_ratio",
                                  std::to_string(b.runout_deep / a.runout_deep));
  std::printf(
      "rotated (%d) / aligned: peak force %.4f, impulse %.4f, run-out %.4f (at depth %.4f), "
      "retained volume %.3f\n",
      k, b.peak_force / a.peak_force, b.impulse / a.impulse, b.runout / a.runout,
      b.runout_deep / a.runout_deep, b.retained / a.retained);
}

/// R = Rz(z) Ry(y) Rx(x) for angles in degrees (the mesh import's convention), written out here
/// so that the tests check the library's.
inline Eigen::Matrix3d rotation_zyx(const Eigen::Vector3d& angles) {
  const double deg = std::numbers::pi / 180.0;
  return (Eigen::AngleAxisd(angles.z() * deg, Eigen::Vector3d::UnitZ()) *
          Eigen::AngleAxisd(angles.y() * deg, Eigen::Vector3d::UnitY()) *
          Eigen::AngleAxisd(angles.x() * deg, Eigen::Vector3d::UnitX()))
      .toRotationMatrix();
}

/// The scene `base` turned by rotation_zyx(angles) about the origin: terrain, barrier, source and
/// gravity, and the grid box around the turned box, on whole cells.
inline nlohmann::json turned_scene(const nlohmann::json& base, const Eigen::Vector3d& angles) {
  const Eigen::Matrix3d R = rotation_zyx(angles);
  nlohmann::json doc = base;
  const nlohmann::json rotate = {angles.x(), angles.y(), angles.z()};
  for (auto& wall : doc["walls"]) {
    if (wall.contains("surface")) wall["surface"]["rotate"] = rotate;  // box faces stay
  }
  for (auto& body : doc["bodies"]) body["shape"]["rotate"] = rotate;
  const Eigen::Vector3d g =
      R * Eigen::Vector3d(base["gravity"][0].get<double>(), base["gravity"][1].get<double>(),
                          base["gravity"][2].get<double>());
  doc["gravity"] = {g.x(), g.y(), g.z()};
  const double h = base["grid"]["spacing"].get<double>();
  Eigen::Vector3d lo = Eigen::Vector3d::Constant(1e300), hi = -lo;
  for (int c = 0; c < 8; ++c) {
    Eigen::Vector3d corner;
    for (int d = 0; d < 3; ++d) {
      corner[d] = base["grid"][(c >> d) & 1 ? "max" : "min"][d].get<double>();
    }
    lo = lo.cwiseMin(R * corner);
    hi = hi.cwiseMax(R * corner);
  }
  for (int d = 0; d < 3; ++d) {
    lo[d] = h * std::floor(lo[d] / h);
    hi[d] = h * std::ceil(hi[d] / h);
  }
  doc["grid"]["min"] = {lo.x(), lo.y(), lo.z()};
  doc["grid"]["max"] = {hi.x(), hi.y(), hi.z()};
  return doc;
}

}  // namespace mpm::test
