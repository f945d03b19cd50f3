// The main scene (data/scenes/debris_wall.json) turned against the grid at a coarse spacing: the
// mesh body's lattice turns with it, and merged Phi multipliers keep the run-out and the barrier's
// impulse. The shipped scene at its own spacing against two turned copies (the bar: peak
// force, run-out, impulse) is test_debris_rotation.cpp.
#include <gtest/gtest.h>

#include <Eigen/Geometry>
#include <filesystem>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "support/debris.hpp"
#include "support/scenes.hpp"

namespace {

using nlohmann::json;
namespace fs = std::filesystem;
using mpm::test::DebrisOutcome;

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
  const Eigen::Matrix3d R = mpm::test::rotation_zyx({17.0, -23.0, 31.0});
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
  const DebrisOutcome a = mpm::test::run_debris(base, "aligned");
  for (std::size_t k = 0; k < rotations.size(); ++k) {
    const DebrisOutcome b = mpm::test::run_debris(mpm::test::turned_scene(base, rotations[k]),
                                                  "rotated" + std::to_string(k));
    mpm::test::expect_turned_outcome_agrees(a, b, static_cast<int>(k), peak_tolerance);
  }
}

// Merged Phi multipliers ("multiplier_radius", docs/blending.md) are grouped along the mesh alone,
// so the turned scene gets the same groups. At h = 1 m (30 s for both runs) its run-out and
// barrier impulse agree as the unmerged scene's do at every spacing (measured with the corner
// rule: 0.995 and 0.987). Its peak force at this spacing is that of a flow reaching the barrier
// one or two cells deep, which the grid does not resolve (docs/debris.md, "Turned against the
// grid": unmerged, 8-18% apart at 0.75 and 1 m; here 0.960); the ratio is recorded and asserted
// only against gross failure (a quarter). The bar on the shipped scene at its own
// spacing is test_debris_rotation.cpp.
TEST(DebrisWall, RotatedSceneWithMergedMultipliersKeepsRunoutAndImpulse) {
  json base = mpm::test::shipped_debris_scene(1.0);
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
