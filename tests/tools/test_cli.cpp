// End-to-end tests of the `mpm` command line: the built executable is run as a user would run it,
// and its exit code, stderr and output directory are checked against the documented contract
// (mpm/run.hpp: 0 done, 2 bad input with nothing written, 3 numerical fault with the output up to
// the fault kept).

#include <fcntl.h>
#include <gtest/gtest.h>
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <map>
#include <regex>
#include <sstream>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "mpm/output.hpp"
#include "mpm/run.hpp"
#include "support/run_mpm.hpp"

namespace fs = std::filesystem;
using nlohmann::json;

namespace {

using namespace mpm::test;  // NOLINT(google-build-using-namespace)

/// A small 2D scene that runs in a few dozen steps: one elastic block falling under gravity
/// above a friction floor, with slip side walls. Tests break one thing in it at a time, so every
/// other key stays valid and the error seen is the one provoked.
json scene_2d() {
  return json::parse(R"({
    "name": "cli_block_2d",
    "dimension": 2,
    "grid": { "min": [0.0, 0.0], "max": [1.0, 1.0], "spacing": 0.1 },
    "shape_function": "bspline2",
    "scheme": { "update": "musl", "transfer": "apic" },
    "gravity": [0.0, -9.81],
    "materials": [
      { "name": "rubber", "model": "neo_hookean", "density": 1000, "youngs_modulus": 1.0e6,
        "poisson_ratio": 0.3 }
    ],
    "bodies": [
      { "name": "block", "material": "rubber",
        "shape": { "type": "box", "min": [0.3, 0.3], "max": [0.7, 0.7] },
        "particles_per_cell": 2 }
    ],
    "walls": [
      { "face": "ymin", "condition": "friction", "mu": 0.3 },
      { "face": "xmin", "condition": "slip" },
      { "face": "xmax", "condition": "slip" }
    ],
    "time": { "end": 0.05, "cfl": 0.5 },
    "output": { "interval": 0.01 }
  })");
}

/// A 1D bar moving so fast to the right that it leaves the grid within a few steps: no walls to
/// stop it, and an end time it can never reach while still inside the box.
json runaway_scene_1d() {
  return json::parse(R"({
    "name": "cli_runaway_1d",
    "dimension": 1,
    "grid": { "min": [0.0], "max": [1.0], "spacing": 0.1 },
    "shape_function": "linear",
    "scheme": { "update": "musl", "transfer": "flip", "flip_blend": 1.0 },
    "materials": [
      { "name": "foam", "model": "linear_elastic", "density": 1.0, "youngs_modulus": 1.0 }
    ],
    "bodies": [
      { "name": "bar", "material": "foam",
        "shape": { "type": "segment", "min": [0.4], "max": [0.6] },
        "velocity": [100.0] }
    ],
    "time": { "end": 1.0 },
    "output": { "interval": 0.001 }
  })");
}

// Every test gets its own directory: ctest runs the tests of this file in parallel, and several
// build trees may run ctest at once, so the name carries both the test name and the pid.
class CommandLine : public ::testing::Test {
 protected:
  void SetUp() override {
    const auto* info = ::testing::UnitTest::GetInstance()->current_test_info();
    dir_ = fs::temp_directory_path() /
           ("mpm_test_cli_" + std::string(info->name()) + "_" + std::to_string(::getpid()));
    fs::remove_all(dir_);
    fs::create_directories(dir_);
    scene_file_ = dir_ / "scene.json";
    out_dir_ = dir_ / "out";
  }
  void TearDown() override { fs::remove_all(dir_); }

  void write_scene(const json& scene) { write_text(scene_file_, scene.dump(2)); }

  /// The summary.json of the last run.
  [[nodiscard]] json read_summary() const {
    return json::parse(read_text(out_dir_ / "summary.json"));
  }

  RunResult run_scene(std::vector<std::string> extra = {}) {
    std::vector<std::string> args{"run", scene_file_.string(), "-o", out_dir_.string(), "-q"};
    args.insert(args.end(), extra.begin(), extra.end());
    return run_mpm(args);
  }

  /// The bad-input contract: exit code 2; exactly one line on stderr of the form
  /// "mpm: FILE: /json/path: what was expected" (so the user can find the spot without
  /// guessing); and no output directory, so nothing that looks like a result is left behind.
  /// `json_path` is matched with its delimiters so "/grid" does not match "/grid/spacing".
  void expect_rejected(const std::string& json_path, const std::vector<std::string>& expected) {
    const RunResult r = run_scene();
    EXPECT_EQ(r.exit_code, 2) << r.err;
    EXPECT_EQ(std::count(r.err.begin(), r.err.end(), '\n'), 1) << "stderr:\n" << r.err;
    EXPECT_FALSE(r.err.empty() || r.err.back() != '\n') << "stderr:\n" << r.err;
    EXPECT_TRUE(contains(r.err, scene_file_.string() + ": " + json_path + ": "))
        << "expected file and JSON path '" << json_path << "' in: " << r.err;
    for (const auto& part : expected) {
      EXPECT_TRUE(contains(r.err, part)) << "expected '" << part << "' in: " << r.err;
    }
    EXPECT_FALSE(fs::exists(out_dir_)) << "bad input must not create " << out_dir_;
  }

  fs::path dir_, scene_file_, out_dir_;
};

// ---------------------------------------------------------------------------------------------
// Bad scenes: one class of mistake per test.

TEST_F(CommandLine, RejectsMissingRequiredKey) {
  json scene = scene_2d();
  scene.erase("grid");
  write_scene(scene);
  // The missing key belongs to the root object, so the path is the root and the key is named.
  expect_rejected("/", {"missing required key", "'grid'"});
}

TEST_F(CommandLine, RejectsMisspelledGridKey) {
  // A typo in a required key must not run with some default spacing; the message must point at
  // the grid object and say which key it needs.
  json scene = scene_2d();
  scene["grid"].erase("spacing");
  scene["grid"]["spacng"] = 0.1;
  write_scene(scene);
  expect_rejected("/grid", {"missing required key", "'spacing'"});
}

TEST_F(CommandLine, RejectsUnknownGridKey) {
  // Every key the user wrote must mean something: an extra key is an error, not ignored.
  json scene = scene_2d();
  scene["grid"]["cells"] = 10;
  write_scene(scene);
  expect_rejected("/grid/cells", {"unknown key", "spacing"});
}

TEST_F(CommandLine, RejectsUnknownTopLevelKey) {
  // "wals" instead of "walls" would silently drop every wall if unknown keys were ignored.
  json scene = scene_2d();
  scene["wals"] = scene["walls"];
  scene.erase("walls");
  write_scene(scene);
  expect_rejected("/wals", {"unknown key", "walls"});
}

TEST_F(CommandLine, RejectsStringWhereNumberExpected) {
  json scene = scene_2d();
  scene["materials"][0]["density"] = "1000";
  write_scene(scene);
  expect_rejected("/materials/0/density", {"expected a number", "\"1000\""});
}

TEST_F(CommandLine, RejectsNegativeDensity) {
  json scene = scene_2d();
  scene["materials"][0]["density"] = -1000.0;
  write_scene(scene);
  expect_rejected("/materials/0/density", {"positive", "-1000"});
}

TEST_F(CommandLine, RejectsACouplingToleranceNoSolveCanMeetOrNoInterfaceCanTrust) {
  // Below 1e-13 the multipliers' own round-off decides when CG stops (it would give up and
  // factorise every step); above 1e-3 the grids' velocities at Phi may disagree by more than a
  // discretisation error. Zero (the user meaning "exact") is one of the former.
  for (const double tolerance : {0.0, 1e-2}) {
    json scene = scene_2d();
    scene["scheme"]["coupling_tolerance"] = tolerance;
    write_scene(scene);
    expect_rejected("/scheme/coupling_tolerance", {"expected a number in [1e-13, 0.001]"});
  }
}

TEST(SceneDefaults, AKeyLeftOutTakesTheDefaultWhetherOrNotItsBlockIsThere) {
  // Read through the library (no output reports these settings): a block written out without
  // its optional keys reads as the block left out, both giving the defaults scene.hpp and
  // walls.hpp declare.
  const mpm::Scene defaults;
  const mpm::BodySpec body_defaults;
  const mpm::WallContact contact_defaults;
  json bare = scene_2d();
  bare.erase("scheme");
  bare["time"].erase("cfl");
  bare["bodies"][0].erase("particles_per_cell");
  bare.erase("output");
  json empty_blocks = bare;
  empty_blocks["scheme"] = json::object();
  empty_blocks["output"] = json::object();
  for (const json& doc : {bare, empty_blocks}) {
    const mpm::Scene scene = mpm::parse_scene(doc, "defaults.json");
    EXPECT_EQ(scene.update, defaults.update);
    EXPECT_EQ(scene.transfer, defaults.transfer);
    EXPECT_EQ(scene.mass_threshold, defaults.mass_threshold);
    EXPECT_EQ(scene.coupling_mass_threshold, defaults.coupling_mass_threshold);
    EXPECT_EQ(scene.coupling_tolerance, defaults.coupling_tolerance);
    EXPECT_EQ(scene.dependence_tolerance, defaults.dependence_tolerance);
    EXPECT_EQ(scene.drop_covered_enhancement, defaults.drop_covered_enhancement);
    EXPECT_EQ(scene.cfl, defaults.cfl);
    EXPECT_EQ(scene.history_interval, defaults.history_interval);
    ASSERT_EQ(scene.bodies.size(), 1U);
    EXPECT_EQ(scene.bodies[0].particles_per_cell, body_defaults.particles_per_cell);
    ASSERT_EQ(scene.walls.size(), 3U);
    EXPECT_EQ(scene.walls[1].contact.separable, contact_defaults.separable);
  }
}

/// scene_2d with the block made of mu(I) sand (Jop et al.'s glass beads).
json scene_2d_mu_i() {
  json scene = scene_2d();
  scene["materials"][0] = json::parse(R"({
    "name": "rubber", "model": "mu_i", "density": 1500, "youngs_modulus": 2.0e6,
    "poisson_ratio": 0.3, "mu_s": 0.38, "mu_2": 0.64, "I_0": 0.279, "grain_diameter": 5e-4,
    "grain_density": 2500 })");
  return scene;
}

TEST_F(CommandLine, RejectsMuIWithDynamicFrictionBelowStatic) {
  // mu(I) rises from mu_s to mu_2 with the inertial number; the other way round is a typo.
  json scene = scene_2d_mu_i();
  scene["materials"][0]["mu_2"] = 0.2;
  write_scene(scene);
  expect_rejected("/materials/0/mu_2", {"[0.38, 10]", "0.2"});
}

TEST_F(CommandLine, RejectsMuIWithoutGrainDiameter) {
  json scene = scene_2d_mu_i();
  scene["materials"][0].erase("grain_diameter");
  write_scene(scene);
  expect_rejected("/materials/0", {"grain_diameter"});
}

TEST_F(CommandLine, RunsMuIScene) {
  write_scene(scene_2d_mu_i());
  const RunResult r = run_scene();
  EXPECT_EQ(r.exit_code, 0) << r.err;
}

TEST_F(CommandLine, RejectsZeroSpacing) {
  json scene = scene_2d();
  scene["grid"]["spacing"] = 0.0;
  write_scene(scene);
  expect_rejected("/grid/spacing", {"positive"});
}

TEST_F(CommandLine, RejectsIncompressiblePoissonRatioIn2D) {
  // nu = 0.5 makes the Lame constant lambda infinite: the wave speed and the time step are
  // meaningless, so it must be refused up front rather than blow up in the first step.
  json scene = scene_2d();
  scene["materials"][0]["poisson_ratio"] = 0.5;
  write_scene(scene);
  expect_rejected("/materials/0/poisson_ratio", {"Poisson ratio", "0.5"});
}

TEST_F(CommandLine, RejectsBodyOutsideGrid) {
  json scene = scene_2d();
  scene["bodies"][0]["shape"]["max"] = {0.7, 1.2};
  write_scene(scene);
  expect_rejected("/bodies/0/shape", {"outside the grid box", "axis 1"});
}

TEST_F(CommandLine, RejectsUnknownMaterialName) {
  json scene = scene_2d();
  scene["bodies"][0]["material"] = "rubbr";
  write_scene(scene);
  expect_rejected("/bodies/0/material", {"\"rubbr\"", "/materials"});
}

TEST_F(CommandLine, RejectsInvalidShapeType) {
  json scene = scene_2d();
  scene["bodies"][0]["shape"]["type"] = "cylinder";
  write_scene(scene);
  // The message lists what the dimension allows (a 2D scene has disks, not spheres).
  expect_rejected("/bodies/0/shape/type", {"\"cylinder\"", "box", "disk"});
}

TEST_F(CommandLine, RejectsVectorOfWrongLengthForDimension) {
  // A 3D gravity vector in a 2D scene: the z component would be silently dropped otherwise.
  json scene = scene_2d();
  scene["gravity"] = {0.0, 0.0, -9.81};
  write_scene(scene);
  expect_rejected("/gravity", {"array of 2 numbers", "dimension 2"});
}

TEST_F(CommandLine, RejectsDuplicateWallFace) {
  json scene = scene_2d();
  scene["walls"].push_back({{"face", "xmin"}, {"condition", "sticky"}});
  write_scene(scene);
  expect_rejected("/walls/3/face", {"second wall", "xmin"});
}

TEST_F(CommandLine, RejectsFrictionCoefficientOnSlipWall) {
  // "mu" on a slip wall suggests the user meant friction; running frictionless would mislead.
  json scene = scene_2d();
  scene["walls"][1]["mu"] = 0.3;
  write_scene(scene);
  expect_rejected("/walls/1/mu", {"friction"});
}

TEST_F(CommandLine, RejectsMlsUpdateWithoutApicOrTheBSpline) {
  // MLS-MPM takes its force and gradient from C_p = B_p D^-1, whose D is constant only for the
  // quadratic B-spline, and C_p is APIC's: with FLIP or another kernel the step would be wrong.
  json scene = scene_2d();
  scene["scheme"] = {{"update", "mls"}, {"transfer", "flip"}};
  write_scene(scene);
  expect_rejected("/scheme/update", {"\"mls\"", "apic", "bspline2"});
  scene = scene_2d();
  scene["scheme"]["update"] = "mls";
  scene["shape_function"] = "gimp";
  write_scene(scene);
  expect_rejected("/scheme/update", {"\"mls\"", "apic", "bspline2"});
}

TEST_F(CommandLine, RejectsTouchToleranceOnBoxWall) {
  // Box walls act on every node near them (standard MPM); accepting the key would mislead.
  json scene = scene_2d();
  scene["walls"][1]["touch_tolerance"] = 0.5;
  write_scene(scene);
  expect_rejected("/walls/1/touch_tolerance", {"dual-grid"});
}

/// scene_2d with its floor as a dual-grid polyline wall named "floor" (one part, "floor").
json scene_2d_dual_floor() {
  json scene = scene_2d();
  scene["walls"][0] = json::parse(R"({
    "name": "floor", "method": "mortar", "condition": "friction", "mu": 0.3,
    "surface": { "type": "polyline", "points": [[0.0, 0.1], [1.0, 0.1]] } })");
  return scene;
}

TEST_F(CommandLine, SummaryReportsTheCouplingsWork) {
  // A block resting in the dual floor's layer: its coupling is assembled and solved every step.
  json scene = scene_2d_dual_floor();
  scene["bodies"][0]["shape"] = {{"type", "box"}, {"min", {0.3, 0.12}}, {"max", {0.7, 0.4}}};
  write_scene(scene);
  RunResult r = run_scene({"-j", "1"});
  ASSERT_EQ(r.exit_code, 0) << r.err;
  json coupling = read_summary().at("coupling").at("floor");
  EXPECT_EQ(coupling.at("method"), "mortar");
  // The floor, 1 m in segments of h = 0.1: 11 Phi nodes, one multiplier each.
  EXPECT_EQ(coupling.at("surface_nodes").get<int>(), 11);
  EXPECT_EQ(coupling.at("multipliers").get<int>(), 11);
  EXPECT_GE(coupling.at("factorizations").get<int>(), 1);
  EXPECT_GE(coupling.at("refinement_passes").get<int>(), 0);
  // Where its time went: four parts, one after another on the thread that couples, within the
  // steps; the first factorisation orders S and factorises it, both timed.
  const json seconds = coupling.at("seconds");
  double parts = 0.0;
  for (const char* part : {"assembly", "analysis", "factorization", "solves"}) {
    EXPECT_GE(seconds.at(part).get<double>(), 0.0) << part;
    parts += seconds.at(part).get<double>();
  }
  EXPECT_GT(seconds.at("analysis").get<double>(), 0.0);
  EXPECT_GT(seconds.at("factorization").get<double>(), 0.0);
  EXPECT_LE(parts, read_summary().at("phase_seconds").at("steps_total").get<double>());
  // Each step couples twice (MUSL, the default, couples its remap too), after the gather or
  // beside it: the adaptive choice tries each way twice before it picks.
  const json summary_mortar = read_summary();
  const json ways = summary_mortar.at("coupling_overlap");
  EXPECT_EQ(ways.at("after").get<long>() + ways.at("beside").get<long>(),
            2 * summary_mortar.at("steps").get<long>());
  EXPECT_GE(ways.at("after").get<long>(), 2);
  EXPECT_GE(ways.at("beside").get<long>(), 2);
  // Merged within h: the greedy pass from the floor's end node makes pairs, 11 -> 6.
  scene["walls"][0]["multiplier_radius"] = 1.0;
  write_scene(scene);
  r = run_scene({"-j", "1", "--overwrite"});
  ASSERT_EQ(r.exit_code, 0) << r.err;
  coupling = read_summary().at("coupling").at("floor");
  EXPECT_EQ(coupling.at("surface_nodes").get<int>(), 11);
  EXPECT_EQ(coupling.at("multipliers").get<int>(), 6);
  EXPECT_FALSE(coupling.contains("active_set"));  // Enhanced only
  // Enhanced: its contact active set too. The resting block (friction, not separable) holds
  // every multiplier in contact and settles each step in a few passes, releasing none.
  scene["walls"][0].erase("multiplier_radius");
  scene["walls"][0]["method"] = "enhanced";
  write_scene(scene);
  r = run_scene({"-j", "1", "--overwrite"});
  ASSERT_EQ(r.exit_code, 0) << r.err;
  const json summary = read_summary();
  coupling = summary.at("coupling").at("floor");
  EXPECT_EQ(coupling.at("method"), "enhanced");
  const json active_set = coupling.at("active_set");
  const int steps = summary.at("steps").get<int>();
  EXPECT_GE(active_set.at("passes").get<int>(), steps);
  EXPECT_LE(active_set.at("passes").get<int>(), 30 * steps);
  EXPECT_EQ(active_set.at("unsettled_steps").get<int>(), 0);
  EXPECT_EQ(active_set.at("kept_released").get<int>(), 0);
}

TEST_F(CommandLine, ResolutionRefinesTheSceneAndAResumedRunKeepsIt) {
  // The dual floor scene at twice the resolution: half the spacing, the same particles per cell
  // (4 times the particles in 2D: the block's faces are on both lattices), the floor cut into
  // segments of the finer h (1 m: 21 nodes).
  json scene = scene_2d_dual_floor();
  scene["bodies"][0]["shape"] = {{"type", "box"}, {"min", {0.3, 0.15}}, {"max", {0.7, 0.4}}};
  write_scene(scene);
  RunResult r = run_scene({"-j", "1"});
  ASSERT_EQ(r.exit_code, 0) << r.err;
  const json coarse = read_summary();
  r = run_scene({"-j", "1", "--overwrite", "--resolution", "2"});
  ASSERT_EQ(r.exit_code, 0) << r.err;
  const json fine = read_summary();
  EXPECT_EQ(coarse.at("resolution").get<int>(), 1);
  EXPECT_EQ(fine.at("resolution").get<int>(), 2);
  EXPECT_DOUBLE_EQ(fine.at("spacing").get<double>(), 0.5 * coarse.at("spacing").get<double>());
  EXPECT_EQ(fine.at("particles").get<int>(), 4 * coarse.at("particles").get<int>());
  EXPECT_EQ(fine.at("coupling").at("floor").at("surface_nodes").get<int>(), 21);
  // The checkpoint remembers the refinement, so `--resume` continues the same run.
  EXPECT_EQ(mpm::checkpoint_origin(out_dir_).resolution, 2);
  // Nonsense is refused before anything is written.
  fs::remove_all(out_dir_);
  r = run_scene({"--resolution", "0"});
  EXPECT_EQ(r.exit_code, 2);
  EXPECT_TRUE(contains(r.err, "--resolution")) << r.err;
  EXPECT_FALSE(fs::exists(out_dir_));
}

TEST_F(CommandLine, RejectsMultiplierRadiusOutOfRangeOrOnEnhancedWall) {
  // Negative or huge radii are typos; Enhanced has no Phi multipliers to merge.
  json scene = scene_2d_dual_floor();
  scene["walls"][0]["multiplier_radius"] = -1.0;
  write_scene(scene);
  expect_rejected("/walls/0/multiplier_radius", {"[0, 8]", "-1"});
  scene["walls"][0]["multiplier_radius"] = 1.0;
  scene["walls"][0]["method"] = "enhanced";
  write_scene(scene);
  expect_rejected("/walls/0/multiplier_radius", {"mortar or one-way"});
}

TEST_F(CommandLine, RejectsUnknownCornerRuleOrOnEnhancedWall) {
  // A misspelt rule would silently leave the default; Enhanced holds Gamma by its multipliers.
  json scene = scene_2d_dual_floor();
  scene["walls"][0]["corners"] = "facet";
  write_scene(scene);
  expect_rejected("/walls/0/corners", {"normal, facets", "facet"});
  scene["walls"][0]["corners"] = "facets";
  scene["walls"][0]["method"] = "enhanced";
  write_scene(scene);
  expect_rejected("/walls/0/corners", {"mortar or one-way"});
}

TEST_F(CommandLine, RejectsConditionForUnknownPart) {
  // A misspelt part would leave the part it meant with the wall's friction.
  json scene = scene_2d_dual_floor();
  scene["walls"][0]["parts"] = {{"flor", {{"condition", "sticky"}}}};
  write_scene(scene);
  expect_rejected("/walls/0/parts/flor", {"no part named \"flor\"", "floor"});
}

TEST_F(CommandLine, RejectsNegativeFrictionOnPart) {
  json scene = scene_2d_dual_floor();
  scene["walls"][0]["parts"] = {{"floor", {{"condition", "friction"}, {"mu", -0.2}}}};
  write_scene(scene);
  expect_rejected("/walls/0/parts/floor/mu", {">= 0"});
}

TEST_F(CommandLine, RejectsSeparableOnPart) {
  // Contact (separable, touch tolerance) is the wall's; a part only changes the condition.
  json scene = scene_2d_dual_floor();
  scene["walls"][0]["parts"] = {{"floor", {{"condition", "slip"}, {"separable", true}}}};
  write_scene(scene);
  expect_rejected("/walls/0/parts/floor/separable", {"unknown key"});
}

TEST_F(CommandLine, RejectsPartsOnSdfWall) {
  json scene = scene_2d_dual_floor();
  scene["walls"][0]["method"] = "sdf";
  scene["walls"][0]["parts"] = {{"floor", {{"condition", "slip"}}}};
  write_scene(scene);
  expect_rejected("/walls/0/parts", {"sdf"});
}

TEST_F(CommandLine, RunsSceneWithPartCondition) {
  json scene = scene_2d_dual_floor();
  scene["walls"][0]["parts"] = {{"floor", {{"condition", "sticky"}}}};
  write_scene(scene);
  const RunResult r = run_scene();
  EXPECT_EQ(r.exit_code, 0) << r.err;
}

TEST_F(CommandLine, RejectsFixedTimeStepAboveCflLimit) {
  // Wave speed of the rubber in 2D is about 37 m/s, so h/c is about 2.7e-3 s; 0.01 s is ~4x over.
  json scene = scene_2d();
  scene["time"]["dt"] = 0.01;
  write_scene(scene);
  expect_rejected("/time/dt", {"limit", "h/c", "0.01"});

  // The limit quoted in the message must be the real one: a step just below it runs.
  const RunResult r = run_scene();
  std::smatch m;
  ASSERT_TRUE(std::regex_search(r.err, m, std::regex(R"(h/c = ([0-9.eE+-]+))"))) << r.err;
  const double limit = std::stod(m[1].str());
  scene["time"]["dt"] = 0.9 * limit;
  write_scene(scene);
  const RunResult ok = run_scene();
  EXPECT_EQ(ok.exit_code, 0) << ok.err;
}

/// A 2 m box in 3D holding a mesh body or a mesh wall given in millimetres.
json millimetre_scene(bool wall) {
  json s = json::parse(R"({
    "dimension": 3,
    "grid": { "min": [0.0, 0.0, 0.0], "max": [2.0, 2.0, 2.0], "spacing": 0.1 },
    "materials": [ { "name": "m", "model": "neo_hookean", "density": 1000,
                     "youngs_modulus": 1.0e6, "poisson_ratio": 0.3 } ],
    "time": { "end": 0.01 }
  })");
  const std::string meshes = std::string(MPM_DATA_DIR) + "/meshes/";
  json body = {{"material", "m"}};
  json shape = {{"type", "mesh"}, {"file", meshes + "unit_cube.obj"}};
  json surface = {{"type", "mesh"}, {"file", meshes + "tilted_plane.obj"}};
  (wall ? surface : shape)["scale"] = 1000.0;
  body["shape"] =
      wall ? json{{"type", "box"}, {"min", {0.5, 0.5, 1.2}}, {"max", {1.0, 1.0, 1.7}}} : shape;
  s["bodies"] = json::array({body});
  if (wall) {
    s["walls"] = json::array(
        {{{"name", "plane"}, {"method", "mortar"}, {"condition", "slip"}, {"surface", surface}}});
  }
  return s;
}

TEST_F(CommandLine, RejectsMeshBodyInMillimetres) {
  // Filling a 1000 m cube on a 0.1 m lattice would never finish; refused before it starts.
  write_scene(millimetre_scene(false));
  expect_rejected("/bodies/0/shape/file", {"unit_cube.obj", "times the grid", "scale 0.001"});
}

TEST_F(CommandLine, RejectsWallMeshInMillimetres) {
  write_scene(millimetre_scene(true));
  expect_rejected("/walls/0/surface", {"tilted_plane.obj", "times the grid", "scale 0.001"});
}

TEST_F(CommandLine, RejectsInvalidJsonSyntax) {
  // A trailing comma on line 3: the message must say where, since the scene is never shown.
  write_text(scene_file_, "{\n  \"dimension\": 2,\n  \"name\": \"x\",\n}\n");
  const RunResult r = run_scene();
  EXPECT_EQ(r.exit_code, 2) << r.err;
  EXPECT_EQ(std::count(r.err.begin(), r.err.end(), '\n'), 1) << r.err;
  EXPECT_TRUE(contains(r.err, scene_file_.string() + ": ")) << r.err;
  EXPECT_TRUE(contains(r.err, "invalid JSON")) << r.err;
  EXPECT_TRUE(std::regex_search(r.err, std::regex("line [0-9]+"))) << r.err;
  EXPECT_FALSE(fs::exists(out_dir_));
}

TEST_F(CommandLine, RejectsMissingSceneFile) {
  const RunResult r = run_scene();  // scene.json was never written
  EXPECT_EQ(r.exit_code, 2) << r.err;
  EXPECT_EQ(std::count(r.err.begin(), r.err.end(), '\n'), 1) << r.err;
  EXPECT_TRUE(contains(r.err, scene_file_.string())) << r.err;
  EXPECT_TRUE(contains(r.err, "does not exist")) << r.err;
  EXPECT_FALSE(fs::exists(out_dir_));
}

TEST_F(CommandLine, RejectsBoxExtentNotMultipleOfSpacing) {
  // Walls sit on the box faces, which must be grid lines: 1.0 is not a whole number of 0.3 cells.
  json scene = scene_2d();
  scene["grid"]["spacing"] = 0.3;
  write_scene(scene);
  expect_rejected("/grid/spacing", {"whole number of cells", "0.3"});
}

// ---------------------------------------------------------------------------------------------
// Command-line parsing.

TEST_F(CommandLine, RequiresSubcommand) {
  const RunResult r = run_mpm({});
  EXPECT_EQ(r.exit_code, 2) << r.err;
  EXPECT_TRUE(contains(r.err, "subcommand")) << r.err;
}

TEST_F(CommandLine, RejectsUnknownOption) {
  write_scene(scene_2d());
  const RunResult r =
      run_mpm({"run", scene_file_.string(), "-o", out_dir_.string(), "--frobnicate"});
  EXPECT_EQ(r.exit_code, 2) << r.err;
  EXPECT_TRUE(contains(r.err, "--frobnicate")) << r.err;
  EXPECT_FALSE(fs::exists(out_dir_)) << "a rejected command line must not run the scene";
}

// `mpm verify`: an unknown case or a malformed case file is bad input (exit 2, one line naming
// it), not a failed check (exit 1).
TEST_F(CommandLine, VerifyRejectsUnknownCase) {
  const RunResult r = run_mpm({"verify", "--case", "no_such_case"});
  EXPECT_EQ(r.exit_code, 2) << r.err;
  EXPECT_TRUE(contains(r.err, "no_such_case")) << r.err;
}

TEST_F(CommandLine, VerifyRejectsMalformedCaseFile) {
  const fs::path dir = out_dir_.parent_path() / "verify_cases";
  fs::create_directories(dir);
  write_text(dir / "bar_impact_1d.json", R"({"methods": ["grid"], "params": {"offset": 0.37}})");
  const RunResult r = run_mpm({"verify", "--case", "bar_impact_1d", "--data", dir.string()});
  EXPECT_EQ(r.exit_code, 2) << r.err;
  EXPECT_TRUE(contains(r.err, "bar_impact_1d.json")) << r.err;
  EXPECT_TRUE(contains(r.err, "spacing")) << r.err;
  fs::remove_all(dir);
}

// `mpm verify --update mls`: the cases run under MLS-MPM; what it cannot run (the bar case's
// linear kernel) is listed as not run, neither passed nor failed, and the rest is checked as
// usual (the particle thrown at the grid and the mortar wall passes at four angles each: exit 0).
TEST_F(CommandLine, VerifyUnderMlsListsTheCasesItCannotRun) {
  const RunResult r =
      run_mpm({"verify", "--update", "mls", "--case", "particle_vs_wall_2d", "--case",
               "bar_impact_1d", "--method", "grid", "--method", "mortar"});
  EXPECT_EQ(r.exit_code, 0) << r.out << r.err;
  EXPECT_TRUE(contains(r.out,
                       "bar_impact_1d          mortar     1  not run: MLS-MPM needs the "
                       "quadratic B-spline"))
      << r.out;
  EXPECT_TRUE(contains(r.out, "8 of 8 checks pass")) << r.out;
  const RunResult bad = run_mpm({"verify", "--update", "flip", "--case", "bar_impact_1d"});
  EXPECT_EQ(bad.exit_code, 2) << bad.err;
  EXPECT_TRUE(contains(bad.err, "--update")) << bad.err;
}

// `mpm bench`: a series, part or configuration that does not exist or does not parse is bad
// input (exit 2, one line naming the file and key), caught before anything runs.
TEST_F(CommandLine, BenchRejectsBadConfigurations) {
  auto expect_one_line = [](const RunResult& r, const std::vector<std::string>& parts) {
    EXPECT_EQ(r.exit_code, 2) << r.err;
    EXPECT_EQ(std::count(r.err.begin(), r.err.end(), '\n'), 1) << r.err;
    for (const auto& part : parts) EXPECT_TRUE(contains(r.err, part)) << part << " in " << r.err;
  };
  expect_one_line(
      run_mpm({"bench", "accuracy", "--cases", "rolling_cylinder_2d", "--cases", "no_such_series"}),
      {"accuracy.json", "no_such_series"});
  expect_one_line(run_mpm({"bench", "stability", "--cases", "no_such_part"}), {"no_such_part"});
  const fs::path config = dir_ / "bench.json";
  write_text(config, R"({"series": [{"case": "bar_impact_1d", "measures": {"bar": "|"},
      "methods": ["grid"], "resolutions": [0], "params": {"spacing": 0.01}}]})");
  expect_one_line(run_mpm({"bench", "accuracy", "--config", config.string()}),
                  {config.string(), "/series/0/resolutions"});
  write_text(config, R"({"limits": {"penetration": 0.25}})");
  expect_one_line(run_mpm({"bench", "stability", "--config", config.string()}),
                  {config.string(), "/limits/energy"});
  write_text(config, "{ not json");
  expect_one_line(run_mpm({"bench", "accuracy", "--config", config.string()}), {config.string()});
}

// `mpm bench`: an option of another kind (perf's to accuracy, stability's to accuracy, the others'
// to perf) is refused, not ignored, and a JSON path that cannot be written fails before perf's
// minute of timing.
TEST_F(CommandLine, BenchPerfRefusesOtherKindsOptionsAndAnUnwritableJson) {
  auto expect_one_line = [](const RunResult& r, int code, const std::vector<std::string>& parts) {
    EXPECT_EQ(r.exit_code, code) << r.err;
    EXPECT_EQ(std::count(r.err.begin(), r.err.end(), '\n'), 1) << r.err;
    for (const auto& part : parts) EXPECT_TRUE(contains(r.err, part)) << part << " in " << r.err;
  };
  expect_one_line(run_mpm({"bench", "perf", "--csv", (dir_ / "perf.csv").string()}), 2,
                  {"--csv", "perf"});
  expect_one_line(run_mpm({"bench", "accuracy", "--smoke", "--cells", "8"}), 2,
                  {"--cells", "accuracy"});
  expect_one_line(run_mpm({"bench", "accuracy", "--smoke", "--seed", "3"}), 2,
                  {"--seed", "accuracy", "stability"});
  const fs::path unwritable = dir_ / "no_such_folder" / "perf.json";
  expect_one_line(run_mpm({"bench", "perf", "--json", unwritable.string()}), 4,
                  {unwritable.string()});
  EXPECT_FALSE(fs::exists(dir_ / "perf.csv"));
}

/// run_mpm() with TMPDIR set to `tmpdir` for the child (it inherits this process's environment),
/// TMPDIR restored afterwards.
RunResult run_mpm_with_tmpdir(const fs::path& tmpdir, const std::vector<std::string>& args) {
  const char* previous = std::getenv("TMPDIR");
  const std::string saved = previous != nullptr ? previous : "";
  ::setenv("TMPDIR", tmpdir.c_str(), 1);
  const RunResult r = run_mpm(args);
  if (previous != nullptr) {
    ::setenv("TMPDIR", saved.c_str(), 1);
  } else {
    ::unsetenv("TMPDIR");
  }
  return r;
}

// Where there is no temporary directory (TMPDIR names a file), `mpm bench` and `mpm verify` stop
// with one line naming TMPDIR's value, exit 4 (bench) or 2 (verify), rather than abort or give
// the library's bare "temp_directory_path: Not a directory": stability works in a folder of it
// (and aborted: only configuration errors were caught), perf writes the floor's mesh there,
// verify the 3D incline's.
TEST_F(CommandLine, CommandsNameATemporaryDirectoryTheyCannotUse) {
  const fs::path not_a_directory = dir_ / "tmp_is_a_file";
  write_text(not_a_directory, "not a directory");
  struct Case {
    std::vector<std::string> args;
    int exit_code;
    std::string command;
  };
  const std::vector<Case> cases = {
      {{"bench", "stability", "--smoke"}, 4, "mpm bench stability"},
      {{"bench", "perf", "--smoke"}, 4, "mpm bench perf"},
      {{"verify", "--case", "incline_block_3d", "--method", "grid"}, 2, "mpm verify"}};
  for (const Case& c : cases) {
    SCOPED_TRACE(c.command);
    const RunResult r = run_mpm_with_tmpdir(not_a_directory, c.args);
    EXPECT_EQ(r.exit_code, c.exit_code) << r.err;
    EXPECT_EQ(std::count(r.err.begin(), r.err.end(), '\n'), 1) << r.err;
    EXPECT_TRUE(contains(r.err, c.command)) << r.err;
    EXPECT_TRUE(contains(r.err, "no temporary directory for")) << r.err;
    EXPECT_TRUE(contains(r.err, "TMPDIR='" + not_a_directory.string() + "'")) << r.err;
  }
}

// --yardstick-script runs the yardstick's script (../shared/tools/yardstick/run.sh) once per
// round of the standard block and divides by the median of the rates it printed for this run's
// thread count. A stand-in script prints known rates (the real one takes seconds) and counts its
// runs: --smoke times one round.
TEST_F(CommandLine, BenchPerfRunsTheYardsticksScriptAndDividesByItsRate) {
  const fs::path script = dir_ / "yard stick's.sh";  // a space and a quote for the shell
  const fs::path count = dir_ / "runs";
  write_text(script, "#!/bin/sh\necho run >> '" + count.string() +
                         "'\necho 'compiling...'\n"
                         "echo 'threads 1 particles 262144 steps 30 time 2.0 s -> 4.00 M "
                         "particle-steps/s'\n"
                         "echo 'threads 2 particles 262144 steps 30 time 1.0 s -> 8.00 M "
                         "particle-steps/s'\n");
  fs::permissions(script, fs::perms::owner_all);
  for (const int threads : {1, 2}) {
    SCOPED_TRACE(threads);
    const fs::path report = dir_ / ("perf" + std::to_string(threads) + ".json");
    fs::remove(count);
    const RunResult r = run_mpm({"bench", "perf", "--smoke", "-j", std::to_string(threads),
                                 "--yardstick-script", script.string(), "--json", report.string()});
    ASSERT_EQ(r.exit_code, 0) << r.err;
    EXPECT_EQ(read_text(count), "run\n");
    const json perf = json::parse(read_text(report));
    EXPECT_EQ(perf["settle"].get<int>(), 5);  // the default
    const double rate = threads == 1 ? 4.0 : 8.0;
    EXPECT_EQ(perf["yardstick"]["median"].get<double>(), rate);
    EXPECT_EQ(perf["yardstick"]["rates"].size(), 1U);
    for (const char* update : {"standard_musl", "standard_usl", "standard_mls"}) {
      const double ours =
          perf[update]["all_threads"]["particle_steps_per_second"].get<double>() * 1e-6;
      EXPECT_NEAR(perf[update]["yardstick_ratio"].get<double>(), ours / rate, 1e-12 * ours / rate);
    }
    // The floor's wall methods against its standard wall, under MUSL and under MLS-MPM.
    for (const char* floor : {"floor", "floor_mls"}) {
      for (const char* method : {"mortar", "one_way", "enhanced", "mortar_merged"}) {
        const json& entry = perf.at(floor).at(method);
        EXPECT_NEAR(entry.at("ratio_to_standard").get<double>(),
                    entry.at("ms_per_step").get<double>() /
                        perf.at(floor).at("standard").at("ms_per_step").get<double>(),
                    1e-12)
            << floor << " " << method;
      }
    }
  }
}

// A yardstick whose first run gives a rate and a later one fails: the benchmark goes on and its
// other results stand, but no throughput ratio is given (none from a median the failure would
// have changed), the JSON says why, and the exit status is 1. Its runs stop at the failure.
TEST_F(CommandLine, BenchPerfDropsTheRatioWhenALaterYardstickRunFails) {
  const fs::path count = dir_ / "runs";
  const fs::path script = dir_ / "second_fails.sh";
  write_text(script, "#!/bin/sh\necho run >> '" + count.string() + "'\n" + "if [ $(wc -l < '" +
                         count.string() + "') -gt 1 ]; then exit 4; fi\n" +
                         "echo 'threads 2 particles 262144 steps 30 time 1.0 s -> 8.00 M "
                         "particle-steps/s'\n");
  fs::permissions(script, fs::perms::owner_all);
  const fs::path report = dir_ / "perf.json";
  const RunResult r =
      run_mpm({"bench", "perf", "--smoke", "--rounds", "3", "--settle", "8", "-j", "2",
               "--yardstick-script", script.string(), "--json", report.string()});
  EXPECT_EQ(r.exit_code, 1) << r.err;
  EXPECT_EQ(read_text(count), "run\nrun\n");  // the first, the failed second, no third
  EXPECT_TRUE(contains(r.err, "exited with status 4")) << r.err;
  EXPECT_TRUE(contains(r.err, "no throughput ratio")) << r.err;
  const json perf = json::parse(read_text(report));
  EXPECT_EQ(perf["rounds"].get<int>(), 3);
  EXPECT_EQ(perf["settle"].get<int>(), 8);
  EXPECT_EQ(perf["yardstick"]["rates"].size(), 1U);
  EXPECT_FALSE(perf["yardstick"].contains("median"));
  EXPECT_TRUE(contains(perf["yardstick"]["error"].get<std::string>(), "exited with status 4"));
  for (const char* update : {"standard_musl", "standard_usl", "standard_mls"}) {
    EXPECT_FALSE(perf[update].contains("yardstick_ratio")) << update;
    EXPECT_GT(perf[update]["all_threads"]["particle_steps_per_second"].get<double>(), 0.0);
  }
}

// A yardstick that cannot be run, fails or prints no rate for the thread count: one line naming
// the script and why, exit 2, and the JSON file as it was (nothing timed, nothing written).
TEST_F(CommandLine, BenchPerfRefusesAYardstickScriptThatGivesNoRate) {
  const fs::path report = dir_ / "perf.json";
  write_text(report, "an earlier report");
  auto expect_refused = [&](const fs::path& script, const std::string& why) {
    SCOPED_TRACE(why);
    const RunResult r = run_mpm({"bench", "perf", "--smoke", "-j", "2", "--yardstick-script",
                                 script.string(), "--json", report.string()});
    EXPECT_EQ(r.exit_code, 2) << r.err;
    EXPECT_EQ(std::count(r.err.begin(), r.err.end(), '\n'), 1) << r.err;
    EXPECT_TRUE(contains(r.err, script.filename().string())) << r.err;
    EXPECT_TRUE(contains(r.err, why)) << r.err;
    EXPECT_EQ(read_text(report), "an earlier report");
  };
  expect_refused(dir_ / "missing.sh", "is not a file");
  const fs::path plain = dir_ / "plain.sh";
  write_text(plain, "#!/bin/sh\necho 'threads 2 x -> 8.00 M particle-steps/s'\n");
  fs::permissions(plain, fs::perms::owner_read | fs::perms::owner_write);
  expect_refused(plain, "is not executable");
  auto script = [&](const std::string& name, const std::string& body) {
    const fs::path path = dir_ / name;
    write_text(path, "#!/bin/sh\n" + body);
    fs::permissions(path, fs::perms::owner_all);
    return path;
  };
  expect_refused(script("fails.sh", "echo 'threads 2 x -> 8.00 M particle-steps/s'\nexit 3\n"),
                 "exited with status 3");
  // Without a "#!" line the shell runs it (as execvp() would), so its own failure is reported,
  // not the kernel's "Exec format error".
  const fs::path bare = dir_ / "no_shebang.sh";
  write_text(bare, "echo 'threads 2 x -> 8.00 M particle-steps/s'\nexit 5\n");
  fs::permissions(bare, fs::perms::owner_all);
  expect_refused(bare, "exited with status 5");
  expect_refused(script("one_thread.sh", "echo 'threads 1 x -> 4.00 M particle-steps/s'\n"),
                 "printed no rate for 2 threads");
  expect_refused(script("garbage.sh", "echo 'threads 2 x -> nan M particle-steps/s'\n"),
                 "printed no rate for 2 threads");
  // With --yardstick as well: which one is meant is not for the command to guess.
  const RunResult both =
      run_mpm({"bench", "perf", "--smoke", "--yardstick", "10", "--yardstick-script",
               script("ok.sh", "echo 'threads 2 x -> 8.00 M particle-steps/s'\n").string()});
  EXPECT_EQ(both.exit_code, 2) << both.err;
  EXPECT_EQ(std::count(both.err.begin(), both.err.end(), '\n'), 1) << both.err;
  EXPECT_TRUE(contains(both.err, "--yardstick")) << both.err;
}

TEST_F(CommandLine, RejectsThreadCountOutOfRange) {
  write_scene(scene_2d());
  const RunResult r = run_mpm({"run", scene_file_.string(), "-o", out_dir_.string(), "-j", "0"});
  EXPECT_EQ(r.exit_code, 2) << r.err;
  EXPECT_FALSE(fs::exists(out_dir_));
}

TEST_F(CommandLine, RequiresOutputDirectory) {
  // Without -o there is nowhere safe to write; the scene must not be run into the cwd.
  write_scene(scene_2d());
  const RunResult r = run_mpm({"run", scene_file_.string()});
  EXPECT_EQ(r.exit_code, 2) << r.err;
  EXPECT_TRUE(contains(r.err, "--output")) << r.err;
}

TEST_F(CommandLine, PrintsHelp) {
  const RunResult r = run_mpm({"--help"});
  EXPECT_EQ(r.exit_code, 0) << r.err;
  EXPECT_TRUE(contains(r.out, "Usage")) << r.out;
  EXPECT_TRUE(contains(r.out, "run")) << r.out;
}

TEST_F(CommandLine, PrintsRunHelp) {
  const RunResult r = run_mpm({"run", "--help"});
  EXPECT_EQ(r.exit_code, 0) << r.err;
  EXPECT_TRUE(contains(r.out, "Usage")) << r.out;
  EXPECT_TRUE(contains(r.out, "--output")) << r.out;
  EXPECT_TRUE(contains(r.out, "--overwrite")) << r.out;
}

TEST_F(CommandLine, PrintsVersion) {
  const RunResult r = run_mpm({"--version"});
  EXPECT_EQ(r.exit_code, 0) << r.err;
  EXPECT_TRUE(std::regex_match(r.out, std::regex("mpm [0-9]+\\.[0-9]+\\.[0-9]+\n"))) << r.out;
}

// ---------------------------------------------------------------------------------------------
// Runs.

TEST_F(CommandLine, RunsSmallScene) {
  write_scene(scene_2d());
  const RunResult r = run_scene({"-j", "1"});
  ASSERT_EQ(r.exit_code, 0) << r.err;
  EXPECT_EQ(r.err, "") << "--quiet and a clean scene: nothing to report";

  const json summary = read_summary();
  EXPECT_EQ(summary.at("status"), "completed");
  EXPECT_GT(summary.at("steps").get<long>(), 0);
  EXPECT_FALSE(summary.contains("error"));
  EXPECT_NEAR(summary.at("simulated_time").get<double>(), 0.05, 1e-12);
  // Where the time went: the phases partition the steps, which with the output take part of the
  // run's wall clock (the rest: loading, setup, the step size, the summary).
  const json& phases = summary.at("phase_seconds");
  double sum = 0.0;
  for (const char* phase : {"locate", "particles_to_grid", "grid_update", "walls", "coupling",
                            "grid_to_particles", "stress", "advect"}) {
    const double seconds = phases.at(phase).get<double>();
    EXPECT_GE(seconds, 0.0) << phase;
    sum += seconds;
  }
  EXPECT_NEAR(phases.at("steps_total").get<double>(), sum, 1e-9 * (1.0 + sum));
  EXPECT_GT(phases.at("particles_to_grid").get<double>(), 0.0);
  EXPECT_GT(phases.at("output").get<double>(), 0.0);
  EXPECT_LE(sum + phases.at("output").get<double>(),
            summary.at("wall_clock_seconds").get<double>());

  const std::string history = read_text(out_dir_ / "history.csv");
  EXPECT_EQ(history.rfind("time,step,dt,kinetic", 0), 0u) << history.substr(0, 80);
  // One row per step plus the header and the t = 0 row (history_interval defaults to every step).
  EXPECT_EQ(std::count(history.begin(), history.end(), '\n'), summary.at("steps").get<long>() + 2);

  EXPECT_TRUE(fs::exists(out_dir_ / "particles.xmf"));
  ASSERT_TRUE(fs::exists(out_dir_ / "particles.h5"));
  const std::size_t frames = mpm::count_frames(out_dir_ / "particles.h5");
  EXPECT_GE(frames, 2u);
  EXPECT_EQ(frames, summary.at("frames_written").get<std::size_t>());
  const mpm::ParticleFrame last = mpm::read_frame(out_dir_ / "particles.h5", frames - 1);
  EXPECT_EQ(last.count, summary.at("particles").get<std::size_t>());
  EXPECT_NEAR(last.time, 0.05, 1e-12);
}

TEST_F(CommandLine, WallImpulsesCloseTheMomentumBalance) {
  // The block set down on the friction floor: over the run the walls' impulses in summary.json
  // (the time integral of the history's forces) must be what momentum balance leaves, the
  // weight's impulse minus the material's momentum at the end (it starts at rest). MPM with
  // APIC conserves momentum in the transfers, so the balance holds to round-off.
  json scene = scene_2d();
  scene["bodies"][0]["shape"]["min"] = {0.3, 0.0};
  scene["bodies"][0]["shape"]["max"] = {0.7, 0.4};
  scene["time"]["end"] = 0.1;
  write_scene(scene);
  const RunResult r = run_scene({"-j", "1"});
  ASSERT_EQ(r.exit_code, 0) << r.err;
  const json summary = read_summary();
  const double mass = summary.at("flow").at("mass_final").get<double>();
  const double T = summary.at("simulated_time").get<double>();
  std::istringstream rows(read_text(out_dir_ / "history.csv"));
  std::string header, line, last;
  std::getline(rows, header);
  while (std::getline(rows, line)) last = line;
  std::vector<std::string> names, values;
  for (auto [text, out] : {std::pair{header, &names}, std::pair{last, &values}}) {
    std::istringstream cells(text);
    for (std::string cell; std::getline(cells, cell, ',');) out->push_back(cell);
  }
  ASSERT_EQ(names.size(), values.size());
  const auto column = [&](const std::string& name) {
    const auto at = std::find(names.begin(), names.end(), name);
    EXPECT_NE(at, names.end()) << name;
    return std::stod(values[static_cast<std::size_t>(at - names.begin())]);
  };
  const double weight = mass * 9.81 * T;
  double impulse[2] = {0.0, 0.0};
  for (const auto& [name, wall] : summary.at("walls").items()) {
    for (int d = 0; d < 2; ++d) impulse[d] += wall.at("impulse_vector")[d].get<double>();
  }
  // Force on the walls: -(what they gave the material) = m g T - p(T), per axis.
  EXPECT_NEAR(impulse[0], -column("momentum_x"), 1e-9 * weight);
  EXPECT_NEAR(impulse[1], -weight - column("momentum_y"), 1e-9 * weight);
  // The floor carried the block for most of the run.
  EXPECT_LT(summary.at("walls").at("ymin").at("impulse_vector")[1].get<double>(), -0.5 * weight);
}

// The run-out at a deposit depth (summary.json flow.runout_at_depth) ignores material thinner
// than that depth. On a slip floor (no horizontal force) an elastic block 0.2 m deep slides at
// 1 m/s and a sheet one particle thick (half a cell, 0.025 m) at 2 m/s ahead of it; APIC carries
// both translations exactly, so after 0.5 s the furthest particle travelled 1.0 m (the sheet) and
// the furthest among those where the deposit is at least 0.1 m deep 0.5 m (the block). The only
// other motion is the block settling under its weight, rho g T / E ~ 2e-5 of its size: the
// tolerance, 1 mm, is far above it and far below the 0.5 m that separates the two answers.
TEST_F(CommandLine, RunoutAtDepthIgnoresAThinSheetThatTravelsFurther) {
  json scene = scene_2d();
  scene["grid"] = {{"min", {0.0, 0.0}}, {"max", {3.0, 0.5}}, {"spacing", 0.05}};
  scene["materials"][0]["youngs_modulus"] = 1.0e7;
  scene["bodies"] = json::array();
  scene["bodies"].push_back({{"name", "block"},
                             {"material", "rubber"},
                             {"shape", {{"type", "box"}, {"min", {0.2, 0.0}}, {"max", {0.6, 0.2}}}},
                             {"velocity", {1.0, 0.0}},
                             {"particles_per_cell", 2}});
  scene["bodies"].push_back(
      {{"name", "sheet"},
       {"material", "rubber"},
       {"shape", {{"type", "box"}, {"min", {1.0, 0.0}}, {"max", {1.4, 0.025}}}},
       {"velocity", {2.0, 0.0}},
       {"particles_per_cell", 2}});
  scene["walls"] = json::array({{{"face", "ymin"}, {"condition", "slip"}}});
  scene["time"]["end"] = 0.5;
  scene["output"] = {{"interval", 0.5}, {"history_interval", 0.5}, {"runout_depths", {0.01, 0.1}}};
  write_scene(scene);
  const RunResult r = run_scene({"-j", "1"});
  ASSERT_EQ(r.exit_code, 0) << r.err;
  const json flow = read_summary().at("flow");
  EXPECT_NEAR(flow.at("runout_distance").get<double>(), 1.0, 1e-3);
  const json& at_depth = flow.at("runout_at_depth");
  ASSERT_EQ(at_depth.size(), 2u);
  EXPECT_EQ(at_depth[0].at("depth").get<double>(), 0.01);
  EXPECT_NEAR(at_depth[0].at("distance").get<double>(), 1.0, 1e-3);  // the sheet is 0.025 deep
  EXPECT_EQ(at_depth[1].at("depth").get<double>(), 0.1);
  EXPECT_NEAR(at_depth[1].at("distance").get<double>(), 0.5, 1e-3);  // the block only
  EXPECT_EQ(at_depth[1].at("radius").get<double>(), 0.1);            // 2 h
}

TEST_F(CommandLine, RejectsNonPositiveRunoutDepth) {
  json scene = scene_2d();
  scene["output"]["runout_depths"] = {0.5, -1.0};
  write_scene(scene);
  expect_rejected("/output/runout_depths/1", {"expected a positive depth in metres", "-1"});
  scene["output"]["runout_depths"] = json::array();
  write_scene(scene);
  expect_rejected("/output/runout_depths", {"expected a non-empty array of depths"});
}

TEST_F(CommandLine, RefusesToOverwriteEarlierResult) {
  write_scene(scene_2d());
  ASSERT_EQ(run_scene().exit_code, 0);
  std::map<fs::path, std::string> before;
  std::map<fs::path, fs::file_time_type> stamps;
  for (const auto& entry : fs::directory_iterator(out_dir_)) {
    before[entry.path()] = read_text(entry.path());
    stamps[entry.path()] = entry.last_write_time();
  }
  ASSERT_TRUE(before.count(out_dir_ / "summary.json"));

  // Another scene into the same directory: without --overwrite the first result must survive.
  json other = scene_2d();
  other["time"]["end"] = 0.02;
  write_scene(other);
  const RunResult refused = run_scene();
  EXPECT_EQ(refused.exit_code, 2) << refused.err;
  EXPECT_EQ(std::count(refused.err.begin(), refused.err.end(), '\n'), 1) << refused.err;
  EXPECT_TRUE(contains(refused.err, "--overwrite")) << refused.err;
  EXPECT_TRUE(contains(refused.err, out_dir_.string())) << refused.err;
  std::size_t after_count = 0;
  for (const auto& entry : fs::directory_iterator(out_dir_)) {
    ++after_count;
    ASSERT_TRUE(before.count(entry.path())) << "new file " << entry.path();
    EXPECT_EQ(read_text(entry.path()), before[entry.path()]) << entry.path() << " was changed";
    EXPECT_EQ(entry.last_write_time(), stamps[entry.path()]) << entry.path() << " was rewritten";
  }
  EXPECT_EQ(after_count, before.size());

  const RunResult replaced = run_scene({"--overwrite"});
  EXPECT_EQ(replaced.exit_code, 0) << replaced.err;
  const json summary = read_summary();
  EXPECT_EQ(summary.at("status"), "completed");
  EXPECT_NEAR(summary.at("end_time").get<double>(), 0.02, 1e-12);
}

TEST_F(CommandLine, RefusesToOverwriteParticlesOfAnInterruptedRun) {
  // A killed run leaves particles.h5 and particles/ but no summary.json; its frames are still a
  // result.
  write_scene(scene_2d());
  fs::create_directories(out_dir_);
  write_text(out_dir_ / "particles.h5", "frames of a killed run");
  const RunResult r = run_scene();
  EXPECT_EQ(r.exit_code, 2) << r.err;
  EXPECT_TRUE(contains(r.err, "--overwrite")) << r.err;
  EXPECT_EQ(read_text(out_dir_ / "particles.h5"), "frames of a killed run");
  EXPECT_FALSE(fs::exists(out_dir_ / "summary.json"));
  // Its frame files alone are a result too (the index can be rebuilt from them).
  fs::remove(out_dir_ / "particles.h5");
  fs::create_directories(out_dir_ / "particles");
  write_text(out_dir_ / "particles" / "000000.h5", "a frame of a killed run");
  const RunResult again = run_scene();
  EXPECT_EQ(again.exit_code, 2) << again.err;
  EXPECT_EQ(read_text(out_dir_ / "particles" / "000000.h5"), "a frame of a killed run");
}

TEST_F(CommandLine, ReportsBodyLeavingGridAsFault) {
  write_scene(runaway_scene_1d());
  const RunResult r = run_scene();
  EXPECT_EQ(r.exit_code, 3) << r.err;
  EXPECT_EQ(std::count(r.err.begin(), r.err.end(), '\n'), 1) << r.err;
  EXPECT_TRUE(contains(r.err, scene_file_.string())) << r.err;
  EXPECT_TRUE(contains(r.err, "particle ")) << r.err;
  EXPECT_TRUE(contains(r.err, "material \"foam\"")) << r.err;
  EXPECT_TRUE(contains(r.err, "left the grid")) << r.err;

  const json summary = read_summary();
  EXPECT_EQ(summary.at("status"), "failed");
  ASSERT_TRUE(summary.contains("error"));
  EXPECT_TRUE(contains(summary.at("error").get<std::string>(), "left the grid"));
  EXPECT_LT(summary.at("simulated_time").get<double>(), summary.at("end_time").get<double>());

  // Everything written before the fault is readable and finite, and ends before the fault.
  const fs::path h5 = out_dir_ / "particles.h5";
  const std::size_t frames = mpm::count_frames(h5);
  EXPECT_GE(frames, 2u);
  EXPECT_EQ(frames, summary.at("frames_written").get<std::size_t>());
  double previous_time = -1.0;
  for (std::size_t i = 0; i < frames; ++i) {
    const mpm::ParticleFrame f = mpm::read_frame(h5, i);
    EXPECT_EQ(f.count, summary.at("particles").get<std::size_t>());
    EXPECT_GT(f.time, previous_time);
    EXPECT_LE(f.time, summary.at("simulated_time").get<double>());
    previous_time = f.time;
    for (std::size_t p = 0; p < f.count; ++p) {
      EXPECT_TRUE(std::isfinite(f.position[3 * p])) << "frame " << i << " particle " << p;
    }
  }
  EXPECT_TRUE(fs::exists(out_dir_ / "particles.xmf"));
}

TEST_F(CommandLine, ReportsRunawayEnergyAsFault) {
  // An elastic block on a slip floor with a fixed step of 0.9 h/c: below the CFL check, but
  // explicit MPM with the B-spline is unstable there, and the energy grows (470 J to 1800 J
  // within 119 steps without the guard, when the CFL check finally trips on the speed). The
  // energy guard stops it first (step 117), naming the fastest particle.
  json scene = json::parse(R"({
    "dimension": 2,
    "grid": { "min": [0.0, 0.0], "max": [1.0, 1.0], "spacing": 0.05 },
    "shape_function": "bspline2",
    "scheme": { "update": "usl", "transfer": "flip", "flip_blend": 1.0 },
    "gravity": [0.0, -9.81],
    "materials": [ { "name": "rubber", "model": "neo_hookean", "density": 1000,
                     "youngs_modulus": 1.0e6, "poisson_ratio": 0.3 } ],
    "bodies": [ { "name": "block", "material": "rubber",
                  "shape": { "type": "box", "min": [0.3, 0.1], "max": [0.7, 0.5] } } ],
    "walls": [ { "face": "ymin", "condition": "slip" } ],
    "time": { "end": 2.0, "dt": 0.0012265 },
    "output": { "interval": 0.5 }
  })");
  write_scene(scene);
  const RunResult r = run_scene();
  EXPECT_EQ(r.exit_code, 3) << r.err;
  EXPECT_EQ(std::count(r.err.begin(), r.err.end(), '\n'), 1) << r.err;
  EXPECT_TRUE(contains(r.err, "runaway energy")) << r.err;
  EXPECT_TRUE(contains(r.err, "material \"rubber\", body \"block\"")) << r.err;
  const json summary = read_summary();
  EXPECT_EQ(summary.at("status"), "failed");
  EXPECT_LT(summary.at("steps").get<long>(), 119) << "before the CFL check would have stopped it";
}

TEST_F(CommandLine, ReportsFixedTimeStepOutgrownByVelocityAsFault) {
  // A steel bar (c = sqrt(E/rho) = 5048 m/s, h/c = 1.981e-6 s) moving at 50 m/s: the fixed step
  // passes the load-time check against h/c but not the run-time one against h/(c + |v|) =
  // 1.962e-6 s. Steps of microseconds are the normal case for metals, so the message must print
  // the step and the limit with enough digits to tell them apart.
  json scene = json::parse(R"({
    "dimension": 1,
    "grid": { "min": [0.0], "max": [1.0], "spacing": 0.01 },
    "materials": [
      { "name": "steel", "model": "linear_elastic", "density": 7850, "youngs_modulus": 2.0e11 }
    ],
    "bodies": [
      { "name": "bar", "material": "steel",
        "shape": { "type": "segment", "min": [0.2], "max": [0.8] }, "velocity": [-50.0] }
    ],
    "time": { "end": 1.0e-4, "dt": 1.97e-6 }
  })");
  write_scene(scene);
  const RunResult r = run_scene();
  EXPECT_EQ(r.exit_code, 3) << r.err;
  EXPECT_EQ(std::count(r.err.begin(), r.err.end(), '\n'), 1) << r.err;
  EXPECT_TRUE(contains(r.err, scene_file_.string())) << r.err;
  EXPECT_TRUE(contains(r.err, "CFL limit")) << r.err;

  std::smatch m;
  ASSERT_TRUE(std::regex_search(
      r.err, m,
      std::regex(R"(time step ([0-9.eE+-]+) is above the CFL limit [^=]*= ([0-9.eE+-]+))")))
      << r.err;
  const double dt = std::stod(m[1].str());
  const double limit = std::stod(m[2].str());
  EXPECT_NEAR(dt, 1.97e-6, 1e-3 * 1.97e-6) << "the step as given in the scene: " << r.err;
  EXPECT_NEAR(limit, 0.01 / (std::sqrt(2.0e11 / 7850.0) + 50.0), 1e-3 * 1.96e-6) << r.err;
  EXPECT_LT(limit, dt) << "the message must show why the step is too large: " << r.err;

  const json summary = read_summary();
  EXPECT_EQ(summary.at("status"), "failed");
  EXPECT_TRUE(contains(summary.value("error", ""), "CFL limit"));
  EXPECT_GE(mpm::count_frames(out_dir_ / "particles.h5"), 1u) << "the initial state is kept";
}

}  // namespace
