// The main scene (data/scenes/debris_wall.json) at a coarse spacing, as shipped and turned by two
// arbitrary rotations (terrain, barrier, source and gravity together): the peak force on the
// barrier, its impulse and the run-out must not depend on how the scene sits against the grid.
#include <gtest/gtest.h>
#include <unistd.h>

#include <Eigen/Geometry>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <numbers>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "mpm/run.hpp"
#include "mpm/scene.hpp"
#include "support/scenes.hpp"

namespace {

using nlohmann::json;
namespace fs = std::filesystem;

const fs::path kScene = fs::path(MPM_DATA_DIR) / "scenes" / "debris_wall.json";

struct Outcome {
  double peak_force = 0.0, peak_time = 0.0, impulse = 0.0, runout = 0.0, runout_deep = 0.0,
         mass_change = 1.0, retained = 0.0;
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
  // The first of the scene's runout_depths (the shipped scene's: two particle layers deep).
  o.runout_deep = summary["flow"]["runout_at_depth"][0]["distance"].get<double>();
  o.mass_change = summary["flow"]["mass_relative_change"].get<double>();
  o.retained =
      summary["flow"]["retaining_walls"]["slope_barrier"]["volume_on_source_side"].get<double>();
  std::printf(
      "%s: peak barrier force %.4g N at %.3f s, barrier impulse %.4g N s, run-out %.4g m "
      "(%.4g m where the deposit is %g m deep), retained %.4g m^3\n",
      label.c_str(), o.peak_force, o.peak_time, o.impulse, o.runout, o.runout_deep,
      summary["flow"]["runout_at_depth"][0]["depth"].get<double>(), o.retained);
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

/// R = Rz(z) Ry(y) Rx(x) for angles in degrees (the mesh import's convention), written out here
/// so that the tests check the library's.
Eigen::Matrix3d rotation(const Eigen::Vector3d& angles) {
  const double deg = std::numbers::pi / 180.0;
  return (Eigen::AngleAxisd(angles.z() * deg, Eigen::Vector3d::UnitZ()) *
          Eigen::AngleAxisd(angles.y() * deg, Eigen::Vector3d::UnitY()) *
          Eigen::AngleAxisd(angles.x() * deg, Eigen::Vector3d::UnitX()))
      .toRotationMatrix();
}

/// The scene `base` turned by rotation(angles) about the origin: terrain, barrier, source and
/// gravity, and the grid box around the turned box.
json turned(const json& base, const Eigen::Vector3d& angles) {
  const Eigen::Matrix3d R = rotation(angles);
  json doc = base;
  const json rotate = {angles.x(), angles.y(), angles.z()};
  for (auto& wall : doc["walls"]) {
    if (wall.contains("surface")) wall["surface"]["rotate"] = rotate;  // box faces stay
  }
  for (auto& body : doc["bodies"]) body["shape"]["rotate"] = rotate;
  const Eigen::Vector3d g =
      R * Eigen::Vector3d(base["gravity"][0].get<double>(), base["gravity"][1].get<double>(),
                          base["gravity"][2].get<double>());
  doc["gravity"] = {g.x(), g.y(), g.z()};
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
  doc["grid"]["min"] = {lo.x(), lo.y(), lo.z()};
  doc["grid"]["max"] = {hi.x(), hi.y(), hi.z()};
  return doc;
}

// "lattice": "body" on a mesh body: the particles are the unplaced mesh's, on the sub-cell lattice
// of its own frame, turned and moved by the placement; with no placement and a grid box starting
// on that lattice they are the grid lattice's (so the shipped scene's particles did not change).
TEST(MeshBodyLattice, TurnsAndMovesWithTheMesh) {
  auto scene = [](const json& placement, const std::string& lattice) {
    json shape = {{"type", "mesh"},
                  {"file", (fs::path(MPM_DATA_DIR) / "meshes" / "unit_cube.obj").string()},
                  {"lattice", lattice}};
    shape.update(placement);
    json doc = mpm::test::box_scene(3, "bspline2", 0.25);
    doc["grid"]["min"] = {-2.0, -2.0, -2.0};
    doc["grid"]["max"] = {2.0, 2.0, 2.0};
    doc["bodies"][0]["shape"] = shape;
    return mpm::test::parse(doc).bodies[0].points;
  };
  const Eigen::Vector3d t(0.3, -0.2, 0.1);
  const Eigen::MatrixX3d own = scene(json::object(), "body");
  const Eigen::MatrixX3d placed =
      scene({{"rotate", {17.0, -23.0, 31.0}}, {"translate", {t.x(), t.y(), t.z()}}}, "body");
  const Eigen::Matrix3d R = rotation({17.0, -23.0, 31.0});
  ASSERT_EQ(own.rows(), 4 * 4 * 4 * 2 * 2 * 2);  // 8^3 sub-cells of 0.125 in the unit cube
  ASSERT_EQ(placed.rows(), own.rows());
  for (Eigen::Index p = 0; p < own.rows(); ++p) {
    const Eigen::Vector3d expected = R * own.row(p).transpose() + t;
    EXPECT_LT((placed.row(p).transpose() - expected).norm(), 1e-13) << "particle " << p;
  }
  // Unplaced, on a box whose corner is on the lattice: the grid's sub-cell centres exactly.
  EXPECT_EQ(scene(json::object(), "grid"), own);
}

/// Runs `base` as it is and turned by each rotation: the bar, the same peak force and
/// run-out within 5% (the peak within `peak_tolerance`), and the barrier's impulse, the momentum
/// the flow brings it.
void expect_turned_scenes_agree(const json& base, const std::vector<Eigen::Vector3d>& rotations,
                                double peak_tolerance = 0.05) {
  const Outcome a = run(base, "aligned");
  // Mass is carried by the particles: exact.
  EXPECT_NEAR(a.mass_change, 0.0, 1e-12);
  // The flow reaches the barrier and loads it.
  EXPECT_GT(a.peak_force, 0.0);
  for (std::size_t k = 0; k < rotations.size(); ++k) {
    const Outcome b = run(turned(base, rotations[k]), "rotated" + std::to_string(k));
    EXPECT_NEAR(b.mass_change, 0.0, 1e-12);
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
        static_cast<int>(k), b.peak_force / a.peak_force, b.impulse / a.impulse,
        b.runout / a.runout, b.runout_deep / a.runout_deep, b.retained / a.retained);
  }
}

TEST(DebrisWall, RotatedSceneGivesSamePeakForceRunoutAndImpulse) {
  const json base = coarse();
  // The shipped scene seeds its source on the lattice of the source mesh's own frame
  // ("lattice": "body"), so turning the scene turns the particles with it; seeded afresh on the
  // grid's lattice the turned source starts as another particle set, and at this spacing (the
  // flow one or two cells deep at the barrier) that alone moved the peak force by 23-43%
  // (docs/debris.md). Measured at this spacing: peak 1.042 and 1.011, run-out 0.997 and 1.001,
  // impulse 1.009 and 1.017.
  ASSERT_EQ(base["bodies"][0]["shape"].value("lattice", "grid"), "body");
  expect_turned_scenes_agree(base, {{17.0, -23.0, 31.0}, {-29.0, 12.0, -47.0}});
}

// Merged Phi multipliers ("multiplier_radius", docs/blending.md) are grouped along the mesh alone,
// so the turned scene gets the same groups. Its run-out and barrier impulse agree as the
// unmerged scene's do (measured: 0.999 and 1.013). Its raw peak force does not meet the 5% bar
// at this spacing (measured 0.920, against 1.042 unmerged: the 0.01 s peak of a flow one or two
// cells deep is a spike, docs/debris.md), which is one reason the option is not the default; the
// ratio is recorded, and asserted only against gross failure (a quarter).
TEST(DebrisWall, RotatedSceneWithMergedMultipliersKeepsRunoutAndImpulse) {
  json base = coarse();
  bool found = false;
  for (auto& wall : base["walls"]) {
    if (wall.value("name", "") != "slope") continue;
    wall["multiplier_radius"] = 1.0;
    found = true;
  }
  ASSERT_TRUE(found);
  expect_turned_scenes_agree(base, {{17.0, -23.0, 31.0}}, 0.25);
}

}  // namespace
