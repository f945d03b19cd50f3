// The main scene (data/scenes/debris_wall.json) at a coarse spacing, as shipped and turned by an
// arbitrary rotation (terrain, barrier, source and gravity together): the run-out must not
// depend on how the scene sits against the grid.
#include <gtest/gtest.h>
#include <unistd.h>

#include <Eigen/Geometry>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <numbers>

#include <nlohmann/json.hpp>

#include "mpm/run.hpp"
#include "mpm/scene.hpp"

namespace {

using nlohmann::json;
namespace fs = std::filesystem;

const fs::path kScene = fs::path(MPM_DATA_DIR) / "scenes" / "debris_wall.json";

struct Outcome {
  double peak_force = 0.0, peak_time = 0.0, impulse = 0.0, runout = 0.0, mass_change = 1.0,
         retained = 0.0;
};

Outcome run(json doc, const std::string& label) {
  // The pid in the name: two build trees (release and sanitizer) may run this test at once.
  const fs::path out =
      fs::temp_directory_path() / ("mpm_test_debris_" + label + "_" + std::to_string(::getpid()));
  const mpm::Scene scene = mpm::parse_scene(doc, kScene);
  mpm::RunOptions options;
  options.out_dir = out;
  options.overwrite = true;
  options.quiet = true;
  EXPECT_EQ(mpm::run_scene(scene, options), 0) << label;
  std::ifstream in(out / "summary.json");
  const json summary = json::parse(in);
  Outcome o;
  o.peak_force = summary["walls"]["slope_barrier"]["peak_force"].get<double>();
  o.peak_time = summary["walls"]["slope_barrier"]["peak_force_time"].get<double>();
  o.impulse = summary["walls"]["slope_barrier"]["impulse"].get<double>();
  o.runout = summary["flow"]["runout_distance"].get<double>();
  o.mass_change = summary["flow"]["mass_relative_change"].get<double>();
  o.retained =
      summary["flow"]["retaining_walls"]["slope_barrier"]["volume_on_source_side"].get<double>();
  std::printf(
      "%s: peak barrier force %.4g N at %.3f s, barrier impulse %.4g N s, run-out %.4g m, "
      "retained %.4g m^3\n",
      label.c_str(), o.peak_force, o.peak_time, o.impulse, o.runout, o.retained);
  fs::remove_all(out);
  return o;
}

/// The shipped scene made small: spacing 1 m, the flow until it has settled against the wall.
json coarse() {
  std::ifstream in(kScene);
  json doc = json::parse(in);
  doc["grid"]["spacing"] = 1.0;
  doc["output"]["interval"] = doc["time"]["end"];
  for (auto& wall : doc["walls"]) {
    if (wall.contains("surface")) wall["surface"].erase("cache");  // leave the user's cache be
  }
  return doc;
}

TEST(DebrisWall, RotatedSceneGivesSameRunoutAndImpulse) {
  const json base = coarse();
  const Outcome a = run(base, "aligned");

  // Turn everything by R = Rz(31) Ry(-23) Rx(17) (the mesh import's convention) about the origin.
  const Eigen::Vector3d angles(17.0, -23.0, 31.0);
  const double deg = std::numbers::pi / 180.0;
  const Eigen::Matrix3d R = (Eigen::AngleAxisd(angles.z() * deg, Eigen::Vector3d::UnitZ()) *
                             Eigen::AngleAxisd(angles.y() * deg, Eigen::Vector3d::UnitY()) *
                             Eigen::AngleAxisd(angles.x() * deg, Eigen::Vector3d::UnitX()))
                                .toRotationMatrix();
  json turned = base;
  const json rotate = {angles.x(), angles.y(), angles.z()};
  for (auto& wall : turned["walls"]) {
    if (wall.contains("surface")) wall["surface"]["rotate"] = rotate;  // box faces stay
  }
  for (auto& body : turned["bodies"]) body["shape"]["rotate"] = rotate;
  const Eigen::Vector3d g =
      R * Eigen::Vector3d(base["gravity"][0].get<double>(), base["gravity"][1].get<double>(),
                          base["gravity"][2].get<double>());
  turned["gravity"] = {g.x(), g.y(), g.z()};
  // The grid box: the turned corners of the original box, on whole cells.
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
  turned["grid"]["min"] = {lo.x(), lo.y(), lo.z()};
  turned["grid"]["max"] = {hi.x(), hi.y(), hi.z()};
  const Outcome b = run(turned, "rotated");

  // Mass is carried by the particles: exact in both.
  EXPECT_NEAR(a.mass_change, 0.0, 1e-12);
  EXPECT_NEAR(b.mass_change, 0.0, 1e-12);
  // The flow reaches the barrier and loads it.
  EXPECT_GT(a.peak_force, 0.0);
  // The same run-out within 5%.
  EXPECT_NEAR(b.runout / a.runout, 1.0, 0.05);
  // The same impulse on the barrier within 5%: the momentum the flow brings it, which the flow
  // down the same slope fixes (measured 2.1% apart at this spacing; a shift of the source by a
  // fraction of a cell alone moves it by 1%).
  EXPECT_NEAR(b.impulse / a.impulse, 1.0, 0.05);
  // The peak barrier force is measured, not asserted: at this spacing (1 m: the flow is one or
  // two cells deep at the barrier) it depends on how the particle lattice samples the flow's
  // front, and a shift of the source by a fraction of a cell, with no rotation, moves it by 23%.
  // The turned/shipped ratio closes with the spacing, 0.58, 0.71, 0.84 at h = 1, 0.75, 0.5 m
  // (docs/debris.md); 5% needs about h = 0.2 m, a run of hours (issue 8 keeps it open).
  RecordProperty("peak_force_ratio", std::to_string(b.peak_force / a.peak_force));
  RecordProperty("impulse_ratio", std::to_string(b.impulse / a.impulse));
  RecordProperty("runout_ratio", std::to_string(b.runout / a.runout));
  std::printf(
      "rotated / aligned: peak force %.3f, impulse %.4f, run-out %.4f, retained volume %.3f\n",
      b.peak_force / a.peak_force, b.impulse / a.impulse, b.runout / a.runout,
      b.retained / a.retained);
}

}  // namespace
