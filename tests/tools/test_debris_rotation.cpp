// Issue 8's rotation bar on the main scene as it ships (data/scenes/debris_wall.json, h = 0.5 m,
// 9 s): turned by two arbitrary rotations (terrain, barrier, source and gravity together, the
// grid box around the turned scene), the peak force on the barrier and the run-out agree within
// 5%, and so does the barrier's impulse. Each run takes minutes, so each is its own ctest entry
// (DebrisWallTurned.Run/<orientation>, a fixture: two run at once under `ctest -j2`) and writes
// what its summary says to MPM_ROTATION_DIR; DebrisWallRotation.SamePeakForceRunoutAndImpulse
// compares them and removes them, so that it never reads an earlier build's runs.
//
// Measured (2026-12-03, the Blending corner rule on; docs/debris.md, "Turned against the grid"):
// turned / shipped peak force 0.985 and 0.993, impulse 0.979 and 0.971, run-out 0.991 and 0.980
// (0.5 m deep: 1.000 and 1.000). At coarser spacings the impact is not resolved (the flow
// reaches the barrier one or two cells deep and its 0.01 s peak is 3 to 5 times this one), and
// the peak differs by 8-18% between orientations there: why the test runs the shipped spacing.
#include <gtest/gtest.h>

#include <Eigen/Core>
#include <array>
#include <filesystem>
#include <fstream>
#include <string>

#include <nlohmann/json.hpp>

#include "support/debris.hpp"

namespace {

using nlohmann::json;
namespace fs = std::filesystem;
using mpm::test::DebrisOutcome;

const fs::path kResults = MPM_ROTATION_DIR;

struct Orientation {
  const char* name;
  Eigen::Vector3d angles;  // degrees, Rz Ry Rx; zero: as shipped
};
const std::array<Orientation, 3> kOrientations = {{{"aligned", {0.0, 0.0, 0.0}},
                                                   {"rotation0", {17.0, -23.0, 31.0}},
                                                   {"rotation1", {-29.0, 12.0, -47.0}}}};

fs::path result_file(const std::string& name) { return kResults / (name + ".json"); }

class DebrisWallTurned : public ::testing::TestWithParam<Orientation> {};

TEST_P(DebrisWallTurned, Run) {
  const Orientation& o = GetParam();
  fs::create_directories(kResults);
  fs::remove(result_file(o.name));
  const json shipped = mpm::test::shipped_debris_scene();
  // The shipped scene seeds its source on the lattice of the source mesh's own frame, so that
  // turning the scene turns its particles (seeded afresh on the grid's lattice, the turned
  // source would be another particle set: docs/debris.md).
  ASSERT_EQ(shipped["bodies"][0]["shape"].value("lattice", "grid"), "body");
  const json doc = o.angles.isZero() ? shipped : mpm::test::turned_scene(shipped, o.angles);
  const DebrisOutcome outcome = mpm::test::run_debris(doc, o.name);
  if (::testing::Test::HasFailure()) return;
  std::ofstream out(result_file(o.name));
  out << json(outcome).dump(2) << '\n';
  ASSERT_TRUE(out.flush()) << result_file(o.name);
}

INSTANTIATE_TEST_SUITE_P(Orientations, DebrisWallTurned, ::testing::ValuesIn(kOrientations),
                         [](const auto& p) { return std::string(p.param.name); });

TEST(DebrisWallRotation, SamePeakForceRunoutAndImpulse) {
  std::array<DebrisOutcome, 3> outcomes;
  for (std::size_t k = 0; k < kOrientations.size(); ++k) {
    const fs::path file = result_file(kOrientations[k].name);
    std::ifstream in(file);
    ASSERT_TRUE(in) << file << " is missing: ctest runs DebrisWallTurned.Run/"
                    << kOrientations[k].name << " (a fixture of this test) first";
    outcomes[k] = json::parse(in).get<DebrisOutcome>();
    in.close();
    fs::remove(file);  // consumed: a later run of this test needs fresh runs
  }
  for (std::size_t k = 1; k < outcomes.size(); ++k) {
    mpm::test::expect_turned_outcome_agrees(outcomes[0], outcomes[k], static_cast<int>(k - 1));
  }
}

}  // namespace
