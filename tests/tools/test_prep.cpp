// `mpm prep` end to end: broken meshes are refused with one line and a non-zero exit, a good mesh
// gives a boundary package that loads back with exact coupling sums and the right layer volume.

#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <string>

#include "mpm/boundary_package.hpp"
#include "support/run_mpm.hpp"

namespace mpm {
namespace {

using namespace mpm::test;  // NOLINT(google-build-using-namespace)

const std::string kBroken = std::string(MPM_DATA_DIR) + "/../tests/data/broken_meshes/";
const std::string kMeshes = std::string(MPM_DATA_DIR) + "/meshes/";

class Prep : public ::testing::Test {
 protected:
  void SetUp() override {
    dir_ = fs::temp_directory_path() /
           ("mpm_test_prep_" +
            std::string(::testing::UnitTest::GetInstance()->current_test_info()->name()) + "_" +
            std::to_string(::getpid()));
    fs::remove_all(dir_);
    fs::create_directories(dir_);
  }
  void TearDown() override { fs::remove_all(dir_); }
  fs::path dir_;
};

struct BrokenCase {
  const char* file;
  const char* defect;  ///< words the one-line message must contain
  bool closed;         ///< run with --closed
};

TEST_F(Prep, RefusesEveryUnrepairableDefectWithOneLine) {
  const BrokenCase cases[] = {
      {"non_manifold_edge.obj", "non-manifold edge", false},
      {"self_intersecting.obj", "self-intersecting", false},
      {"open_box.obj", "open surface", true},
      {"nan_vertex.obj", "non-finite coordinate", false},
  };
  for (const auto& c : cases) {
    const fs::path out = dir_ / "package.h5";
    std::vector<std::string> args{"prep", kBroken + c.file, "--spacing", "0.25",
                                  "-o",   out.string()};
    if (c.closed) args.emplace_back("--closed");
    const RunResult r = run_mpm(args);
    EXPECT_EQ(r.exit_code, 2) << c.file << ": " << r.err;
    EXPECT_TRUE(contains(r.err, c.file)) << r.err;
    EXPECT_TRUE(contains(r.err, c.defect)) << r.err;
    EXPECT_EQ(std::count(r.err.begin(), r.err.end(), '\n'), 1) << r.err;
    EXPECT_FALSE(fs::exists(out)) << c.file;
  }
}

TEST_F(Prep, RepairsWhatCanBeRepaired) {
  for (const char* file : {"degenerate_face.obj", "duplicate_face.obj", "flipped_face.obj",
                           "inward_cube.obj", "split_seam.obj", "open_box.obj"}) {
    const fs::path out = dir_ / (std::string(file) + ".h5");
    const RunResult r =
        run_mpm({"prep", kBroken + file, "--spacing", "0.25", "--no-remesh", "-o", out.string()});
    EXPECT_EQ(r.exit_code, 0) << file << ": " << r.err;
    EXPECT_TRUE(fs::exists(out)) << file;
  }
}

TEST_F(Prep, MissingMeshAndBadOptionsExitTwo) {
  const fs::path out = dir_ / "p.h5";
  RunResult r = run_mpm({"prep", "no/such/mesh.stl", "--spacing", "0.1", "-o", out.string()});
  EXPECT_EQ(r.exit_code, 2);
  EXPECT_TRUE(contains(r.err, "no/such/mesh.stl")) << r.err;
  r = run_mpm({"prep", kMeshes + "tilted_plane.obj", "--spacing", "-1", "-o", out.string()});
  EXPECT_EQ(r.exit_code, 2);
  r = run_mpm({"prep", kMeshes + "tilted_plane.obj", "--spacing", "0.1", "--layers", "0", "-o",
               out.string()});
  EXPECT_EQ(r.exit_code, 2);
  EXPECT_FALSE(fs::exists(out));
}

TEST_F(Prep, RefusesARemeshTooLargeForMemory) {
  // A 1 m plane given in millimetres, remeshed at 5 mm: about 1e11 triangles, which would be
  // killed for memory hours later; refused at once with the count and the likely cause.
  const fs::path out = dir_ / "p.h5";
  const RunResult r = run_mpm({"prep", kMeshes + "tilted_plane.obj", "--spacing", "0.005",
                               "--scale", "1000", "-o", out.string()});
  EXPECT_EQ(r.exit_code, 2);
  EXPECT_EQ(std::count(r.err.begin(), r.err.end(), '\n'), 1) << r.err;
  EXPECT_TRUE(contains(r.err, "tilted_plane.obj")) << r.err;
  EXPECT_TRUE(contains(r.err, "triangles")) << r.err;
  EXPECT_FALSE(fs::exists(out));
}

TEST_F(Prep, KeepsAnExistingPackageUnlessTold) {
  const fs::path out = dir_ / "plane.h5";
  const std::vector<std::string> args{
      "prep", kMeshes + "tilted_plane.obj", "--spacing", "0.1", "-o", out.string()};
  ASSERT_EQ(run_mpm(args).exit_code, 0);
  const auto before = fs::last_write_time(out);
  const RunResult again = run_mpm(args);
  EXPECT_EQ(again.exit_code, 2);
  EXPECT_TRUE(contains(again.err, "--overwrite")) << again.err;
  EXPECT_EQ(fs::last_write_time(out), before);
  std::vector<std::string> forced = args;
  forced.emplace_back("--overwrite");
  EXPECT_EQ(run_mpm(forced).exit_code, 0);
}

// The tilted plane (2 m x 1 m): the layer over a plane has volume area * t, and every coupling
// column sums to the integral of its multiplier (partition of unity of the grid basis over Phi and
// Gamma).
TEST_F(Prep, PackageOfAPlaneLoadsBackExact) {
  const fs::path out = dir_ / "plane.h5";
  const RunResult r = run_mpm({"prep", kMeshes + "tilted_plane.obj", "--spacing", "0.1",
                               "--thickness", "0.1", "-o", out.string()});
  ASSERT_EQ(r.exit_code, 0) << r.err;
  EXPECT_TRUE(contains(r.out, "Gamma area")) << r.out;
  ASSERT_TRUE(fs::exists(dir_ / "plane.xmf"));
  EXPECT_TRUE(contains(read_text(dir_ / "plane.xmf"), "plane.h5:/xdmf/cells"));

  const BoundaryPackage p = load_boundary_package(out);
  EXPECT_EQ(p.layer.dimension, 3);
  EXPECT_NEAR(p.report.wall_measure, 2.0, 1e-5);  // float positions from assimp
  // Positions pass through assimp as float, so the file's plane is flat only to ~1e-7 relative
  // (the exact 1e-9 checks on double-precision planes are in test_boundary_grid).
  EXPECT_NEAR(p.report.volume, p.report.wall_measure * 0.1, 1e-6 * p.report.volume);
  EXPECT_NEAR(p.report.interface_measure, p.report.wall_measure, 1e-6 * p.report.wall_measure);
  for (const mpmgeom::Coupling* c : {&p.interface_coupling, &p.wall_coupling}) {
    ASSERT_EQ(c->grid.cols(), static_cast<Eigen::Index>(c->multiplier_node.size()));
    EXPECT_EQ(c->grid.rows(), p.grid.node_count());
    for (Eigen::Index mu = 0; mu < c->grid.cols(); ++mu) {
      const double sum = c->grid.col(mu).sum();
      ASSERT_NEAR(sum, c->multiplier_integral[mu], 1e-12 * c->multiplier_integral[mu]);
      ASSERT_NEAR(c->boundary.col(mu).sum(), c->multiplier_integral[mu],
                  1e-12 * c->multiplier_integral[mu]);
    }
  }
  std::size_t flagged = 0;
  for (auto f : p.cell_flags) flagged += f;
  EXPECT_GT(flagged, 0U);
}

TEST_F(Prep, RoundTripPreservesEverything) {
  const fs::path out = dir_ / "chute.h5";
  ASSERT_EQ(run_mpm({"prep", kMeshes + "chute_half_cylinder.obj", "--spacing", "0.2", "--layers",
                     "2", "-o", out.string()})
                .exit_code,
            0);
  const BoundaryPackage a = load_boundary_package(out);
  save_boundary_package(a, dir_ / "copy.h5", dir_ / "copy.xmf");
  const BoundaryPackage b = load_boundary_package(dir_ / "copy.h5");
  EXPECT_EQ(a.layer.nodes, b.layer.nodes);
  EXPECT_EQ(a.layer.cells, b.layer.cells);
  EXPECT_EQ(a.layer.layers, 2);
  EXPECT_EQ(a.layer.part_names, b.layer.part_names);
  EXPECT_EQ(a.layer.interface_facets, b.layer.interface_facets);
  EXPECT_EQ(a.source_digest, b.source_digest);
  EXPECT_EQ(a.cell_flags, b.cell_flags);
  EXPECT_TRUE(a.interface_coupling.grid.isApprox(b.interface_coupling.grid, 0.0));
  EXPECT_TRUE(a.wall_coupling.boundary.isApprox(b.wall_coupling.boundary, 0.0));
}

// A package is written aside and renamed: a write that fails leaves the old files whole and no
// temporary file behind, and says which file it could not write.
TEST_F(Prep, FailedSaveKeepsTheOldPackageAndLeavesNoTemporaryFile) {
  const fs::path out = dir_ / "chute.h5";
  ASSERT_EQ(
      run_mpm({"prep", kMeshes + "chute_half_cylinder.obj", "--spacing", "0.2", "-o", out.string()})
          .exit_code,
      0);
  const BoundaryPackage a = load_boundary_package(out);
  const fs::path copy = dir_ / "copy.h5", xmf = dir_ / "copy.xmf";
  save_boundary_package(a, copy, xmf);
  EXPECT_FALSE(fs::exists(dir_ / "copy.h5.tmp"));
  EXPECT_FALSE(fs::exists(dir_ / "copy.xmf.tmp"));
  const std::string before = read_text(copy);

  // The HDF5 file cannot be created (its temporary name is taken by a directory that is not
  // empty, which no test run as root can be kept from writing otherwise).
  fs::create_directories(dir_ / "copy.h5.tmp" / "taken");
  try {
    save_boundary_package(a, copy, xmf);
    FAIL() << "expected an exception";
  } catch (const std::runtime_error& e) {
    EXPECT_TRUE(contains(e.what(), "copy.h5")) << e.what();
  }
  EXPECT_EQ(read_text(copy), before);
  EXPECT_TRUE(load_boundary_package(copy).layer.nodes.isApprox(a.layer.nodes, 0.0));
  fs::remove_all(dir_ / "copy.h5.tmp");

  // The XDMF index cannot be written (its directory does not exist): named, and nothing left.
  const fs::path missing = dir_ / "no_such_dir" / "copy.xmf";
  try {
    save_boundary_package(a, copy, missing);
    FAIL() << "expected an exception";
  } catch (const std::runtime_error& e) {
    EXPECT_TRUE(contains(e.what(), "copy.xmf")) << e.what();
  }
  EXPECT_FALSE(fs::exists(dir_ / "copy.h5.tmp"));
  EXPECT_EQ(read_text(copy), before);  // the same package written again: the same bytes
}

TEST_F(Prep, LoadingSomethingElseFailsWithTheFileName) {
  write_text(dir_ / "not.h5", "plain text");
  try {
    (void)load_boundary_package(dir_ / "not.h5");
    FAIL() << "expected an exception";
  } catch (const std::runtime_error& e) {
    EXPECT_TRUE(contains(e.what(), "not.h5")) << e.what();
  }
}

}  // namespace
}  // namespace mpm
