// Tests for mpmgeom::validate_and_repair and mpmgeom::remesh_isotropic: meshes built in code
// (cube, icosphere, grid plane) and the one-defect files in tests/data/broken_meshes, each
// loaded with load_mesh and checked for its exact outcome: what was repaired, or the message.

#include "mpmgeom/mesh_repair.hpp"
#include "mpmgeom/triangle_mesh.hpp"
#include "support/shapes.hpp"

#include <gtest/gtest.h>

#include <algorithm>
#include <array>
#include <cmath>
#include <filesystem>
#include <functional>
#include <limits>
#include <map>
#include <numbers>
#include <set>
#include <stdexcept>
#include <string>
#include <utility>
#include <vector>

namespace {

namespace fs = std::filesystem;
using mpm::test::icosphere;
using mpmgeom::load_mesh;
using mpmgeom::MeshError;
using mpmgeom::remesh_isotropic;
using mpmgeom::RepairOptions;
using mpmgeom::RepairReport;
using mpmgeom::TriangleMesh;
using mpmgeom::validate_and_repair;

const fs::path kBroken = fs::path(MPM_DATA_DIR).parent_path() / "tests" / "data" / "broken_meshes";

// ---------------------------------------------------------------------------------------------
// Meshes built in code

// Unit cube [0,1]^3, 12 triangles wound counter-clockwise seen from outside (as
// data/meshes/unit_cube.obj), one part.
TriangleMesh cube() {
  TriangleMesh m;
  m.V.resize(8, 3);
  m.V << 0, 0, 0, 1, 0, 0, 1, 1, 0, 0, 1, 0, 0, 0, 1, 1, 0, 1, 1, 1, 1, 0, 1, 1;
  m.F.resize(12, 3);
  m.F << 0, 3, 2, 0, 2, 1, 4, 5, 6, 4, 6, 7, 0, 1, 5, 0, 5, 4, 3, 7, 6, 3, 6, 2, 0, 4, 7, 0, 7, 3,
      1, 2, 6, 1, 6, 5;
  m.part = Eigen::VectorXi::Zero(12);
  m.part_names = {"cube"};
  return m;
}

// The unit square z = 0 as n x n cells of two triangles, normals +z; faces left of x = 0.5 are
// part 0 ("left"), the others part 1 ("right"). n must be even.
TriangleMesh grid_plane(int n) {
  TriangleMesh m;
  m.V.resize((n + 1) * (n + 1), 3);
  for (int j = 0; j <= n; ++j) {
    for (int i = 0; i <= n; ++i) m.V.row(j * (n + 1) + i) << double(i) / n, double(j) / n, 0.0;
  }
  m.F.resize(2 * n * n, 3);
  m.part.resize(2 * n * n);
  for (int j = 0; j < n; ++j) {
    for (int i = 0; i < n; ++i) {
      const int a = j * (n + 1) + i, b = a + 1, c = a + n + 2, d = a + n + 1;
      const int f = 2 * (j * n + i);
      m.F.row(f) << a, b, c;
      m.F.row(f + 1) << a, c, d;
      m.part(f) = m.part(f + 1) = 2 * i < n ? 0 : 1;
    }
  }
  m.part_names = {"left", "right"};
  return m;
}

// ---------------------------------------------------------------------------------------------
// Measures

Eigen::Vector3d corner(const TriangleMesh& m, Eigen::Index f, int k) {
  return m.V.row(m.F(f, k)).transpose();
}

Eigen::Vector3d normal(const TriangleMesh& m, Eigen::Index f) {  // twice the area
  return (corner(m, f, 1) - corner(m, f, 0)).cross(corner(m, f, 2) - corner(m, f, 0));
}

Eigen::Vector3d centroid(const TriangleMesh& m, Eigen::Index f) {
  return (corner(m, f, 0) + corner(m, f, 1) + corner(m, f, 2)) / 3.0;
}

// Positive iff the faces of a closed surface point out of the volume.
double signed_volume(const TriangleMesh& m) {
  double six_v = 0.0;
  for (Eigen::Index f = 0; f < m.F.rows(); ++f) {
    six_v += corner(m, f, 0).dot(corner(m, f, 1).cross(corner(m, f, 2)));
  }
  return six_v / 6.0;
}

// Every face points away from `inside` (true for a convex surface oriented outward).
bool faces_point_away_from(const TriangleMesh& m, const Eigen::Vector3d& inside) {
  for (Eigen::Index f = 0; f < m.F.rows(); ++f) {
    if (normal(m, f).dot(centroid(m, f) - inside) <= 0.0) return false;
  }
  return true;
}

// Each undirected edge once, with the faces on it.
std::map<std::pair<int, int>, std::vector<Eigen::Index>> edges(const TriangleMesh& m) {
  std::map<std::pair<int, int>, std::vector<Eigen::Index>> out;
  for (Eigen::Index f = 0; f < m.F.rows(); ++f) {
    for (int k = 0; k < 3; ++k) out[std::minmax(m.F(f, k), m.F(f, (k + 1) % 3))].push_back(f);
  }
  return out;
}

double mean_edge_length(const TriangleMesh& m) {
  double sum = 0.0;
  const auto all = edges(m);
  for (const auto& [e, faces] : all) sum += (m.V.row(e.first) - m.V.row(e.second)).norm();
  return sum / static_cast<double>(all.size());
}

double min_face_area(const TriangleMesh& m) {
  double smallest = std::numeric_limits<double>::infinity();
  for (Eigen::Index f = 0; f < m.F.rows(); ++f)
    smallest = std::min(smallest, 0.5 * normal(m, f).norm());
  return smallest;
}

void expect_nothing_repaired(const RepairReport& r) {
  EXPECT_EQ(r.degenerate_faces_removed, 0u);
  EXPECT_EQ(r.duplicate_faces_removed, 0u);
  EXPECT_EQ(r.faces_reoriented, 0u);
  EXPECT_EQ(r.inward_faces_reversed, 0u);
  EXPECT_EQ(r.edges_stitched, 0u);
  EXPECT_TRUE(r.repairs.empty()) << r.repairs.front();
}

::testing::AssertionResult contains(const std::string& text, const std::string& part) {
  if (text.find(part) != std::string::npos) return ::testing::AssertionSuccess();
  return ::testing::AssertionFailure() << "'" << text << "' does not contain '" << part << "'";
}

// Runs `call`, expects a MeshError and returns its message.
std::string error_of(const std::function<void()>& call) {
  try {
    call();
  } catch (const MeshError& e) {
    return e.what();
  }
  ADD_FAILURE() << "expected a MeshError";
  return {};
}

// load_mesh + validate_and_repair, named after the file as `mpm prep` does.
TriangleMesh repair_file(const std::string& file, RepairReport& report,
                         const RepairOptions& options = {}) {
  const fs::path path = kBroken / file;
  return validate_and_repair(load_mesh(path), path.string(), options, &report);
}

std::string error_of_file(const std::string& file, const RepairOptions& options = {}) {
  return error_of([&] {
    RepairReport report;
    repair_file(file, report, options);
  });
}

const Eigen::Vector3d kCubeCentre(0.5, 0.5, 0.5);

// ---------------------------------------------------------------------------------------------
// validate_and_repair on meshes built in code

TEST(MeshRepair, ValidIcospherePassesUntouched) {
  const TriangleMesh sphere = icosphere(3);
  ASSERT_GT(signed_volume(sphere), 0.0);
  RepairReport report;
  const TriangleMesh out = validate_and_repair(sphere, "sphere", {.require_closed = true}, &report);
  expect_nothing_repaired(report);
  EXPECT_EQ(report.components, 1u);
  EXPECT_EQ(report.border_edges, 0u);
  EXPECT_EQ(report.self_intersecting_pairs, 0u);
  EXPECT_TRUE(report.closed);
  EXPECT_TRUE(report.outward);
  EXPECT_EQ(out.V, sphere.V);
  EXPECT_EQ(out.F, sphere.F);
  EXPECT_EQ(out.part, sphere.part);
  EXPECT_EQ(out.part_names, sphere.part_names);
}

TEST(MeshRepair, ReportArgumentIsOptional) {
  const TriangleMesh out = validate_and_repair(cube(), "cube");
  EXPECT_EQ(out.F, cube().F);
}

TEST(MeshRepair, MeshWithoutPartsGetsOnePart) {
  TriangleMesh m = cube();
  m.part.resize(0);
  m.part_names.clear();
  const TriangleMesh out = validate_and_repair(m, "cube");
  EXPECT_EQ(out.part, Eigen::VectorXi::Zero(12));
  EXPECT_EQ(out.part_names, std::vector<std::string>{"mesh"});
}

TEST(MeshRepair, NonFiniteVertexIsRejected) {
  TriangleMesh m = cube();
  m.V(7, 1) = std::numeric_limits<double>::quiet_NaN();
  const std::string message = error_of([&] { validate_and_repair(m, "cube.obj"); });
  EXPECT_TRUE(contains(message, "mesh 'cube.obj': non-finite coordinate at vertex 7"));
  m.V(7, 1) = std::numeric_limits<double>::infinity();
  EXPECT_TRUE(contains(error_of([&] { validate_and_repair(m, "cube.obj"); }),
                       "non-finite coordinate at vertex 7"));
}

TEST(MeshRepair, InconsistentArraysAreRejected) {
  TriangleMesh m = cube();
  m.F(3, 1) = 8;
  EXPECT_EQ(error_of([&] { validate_and_repair(m, "c"); }),
            "mesh 'c': face 3 references vertex 8 of 8");
  m = cube();
  m.part(5) = 1;
  EXPECT_EQ(error_of([&] { validate_and_repair(m, "c"); }), "mesh 'c': face 5 has part 1 of 1");
  m = cube();
  m.F.resize(0, 3);
  EXPECT_EQ(error_of([&] { validate_and_repair(m, "c"); }), "mesh 'c': contains no triangles");
}

TEST(MeshRepair, ExactlyDuplicatedSeamIsStitched) {
  // The top face gets its own copies of the four top corners (vertices 8-11).
  TriangleMesh m = cube();
  m.V.conservativeResize(12, 3);
  m.V.bottomRows(4) = m.V.middleRows(4, 4);
  m.F.row(2) << 8, 9, 10;
  m.F.row(3) << 8, 10, 11;
  RepairReport report;
  const TriangleMesh out = validate_and_repair(m, "seam", {.require_closed = true}, &report);
  EXPECT_EQ(report.edges_stitched, 4u);
  EXPECT_EQ(report.repairs.size(), 1u);
  EXPECT_TRUE(report.closed);
  EXPECT_EQ(out.V, cube().V);
  EXPECT_EQ(out.F, cube().F);
}

TEST(MeshRepair, SeamWiderThanStitchToleranceStaysOpen) {
  TriangleMesh m = cube();
  m.V.conservativeResize(12, 3);
  m.V.bottomRows(4) = m.V.middleRows(4, 4);
  m.V.bottomRows(4).col(2).array() += 1e-3;
  m.F.row(2) << 8, 9, 10;
  m.F.row(3) << 8, 10, 11;
  RepairReport report;
  validate_and_repair(m, "gap", {}, &report);
  EXPECT_EQ(report.edges_stitched, 0u);
  EXPECT_FALSE(report.closed);
  EXPECT_EQ(report.border_edges, 8u);
  EXPECT_EQ(report.components, 2u);
  // A tolerance above the gap closes it.
  validate_and_repair(m, "gap", {.stitch_tolerance = 2e-3}, &report);
  EXPECT_EQ(report.edges_stitched, 4u);
  EXPECT_TRUE(report.closed);
}

TEST(MeshRepair, NonManifoldVertexIsRejected) {
  // Two tetrahedra touching at the origin only.
  TriangleMesh m;
  m.V.resize(7, 3);
  m.V << 0, 0, 0, 1, 0, 0, 0, 1, 0, 0, 0, 1, -1, 0, 0, 0, -1, 0, 0, 0, -1;
  m.F.resize(8, 3);
  m.F << 0, 2, 1, 0, 1, 3, 0, 3, 2, 1, 2, 3, 0, 5, 4, 0, 4, 6, 0, 6, 5, 4, 5, 6;
  const std::string message = error_of([&] { validate_and_repair(m, "pinch.stl"); });
  EXPECT_TRUE(contains(message, "mesh 'pinch.stl': 1 non-manifold vertex (first at (0, 0, 0)"));
}

TEST(MeshRepair, MoebiusStripIsRejected) {
  // A band of 20 quads whose ends are glued with a half twist: no consistent orientation.
  const int n = 20;
  TriangleMesh m;
  m.V.resize(2 * n, 3);
  for (int i = 0; i < n; ++i) {
    const double angle = 2.0 * std::numbers::pi * i / n;
    for (int side = 0; side < 2; ++side) {
      const double w = side == 0 ? -0.2 : 0.2;
      const double r = 1.0 + w * std::cos(angle / 2.0);
      m.V.row(2 * i + side) << r * std::cos(angle), r * std::sin(angle), w * std::sin(angle / 2.0);
    }
  }
  m.F.resize(2 * n, 3);
  for (int i = 0; i < n; ++i) {
    const int a = 2 * i, b = 2 * i + 1;
    // After the last quad the two sides swap: the half twist.
    const int next_a = i + 1 < n ? a + 2 : 1, next_b = i + 1 < n ? b + 2 : 0;
    m.F.row(2 * i) << a, next_a, next_b;
    m.F.row(2 * i + 1) << a, next_b, b;
  }
  EXPECT_TRUE(contains(error_of([&] { validate_and_repair(m, "strip.obj"); }),
                       "mesh 'strip.obj': cannot be oriented consistently"));
}

TEST(MeshRepair, NothingLeftIsRejected) {
  TriangleMesh m;
  m.V.resize(4, 3);
  m.V << 0, 0, 0, 1, 0, 0, 2, 0, 0, 0, 1, 0;
  m.F.resize(2, 3);
  m.F << 0, 1, 2, 0, 3, 3;  // collinear corners; a repeated corner
  EXPECT_EQ(error_of([&] { validate_and_repair(m, "dust.obj"); }),
            "mesh 'dust.obj': no triangles left after removing 2 degenerate faces");
}

TEST(MeshRepair, PartsFollowTheirFaces) {
  // The inward cube with two parts, one face listed twice with another part: faces keep their
  // parts through reversal, and the first of two duplicates wins.
  TriangleMesh m = cube();
  m.F.col(1).swap(m.F.col(2));
  for (Eigen::Index f = 0; f < 12; ++f) m.part(f) = f < 6 ? 0 : 1;
  m.part_names = {"lower", "upper"};
  m.F.conservativeResize(13, 3);
  m.F.row(12) = m.F.row(11);
  m.part.conservativeResize(13);
  m.part(12) = 0;
  RepairReport report;
  const TriangleMesh out = validate_and_repair(m, "parts", {}, &report);
  EXPECT_EQ(report.duplicate_faces_removed, 1u);
  EXPECT_EQ(report.inward_faces_reversed, 12u);
  ASSERT_EQ(out.F.rows(), 12);
  EXPECT_EQ(out.part, m.part.head(12));
  EXPECT_EQ(out.part_names, m.part_names);
  EXPECT_TRUE(faces_point_away_from(out, kCubeCentre));
}

TEST(MeshRepair, NestedShellsBoundTheVolumeBetweenThem) {
  // A hollow ball: both shells come in pointing outward; the inner one must point into the
  // cavity, away from the material between the shells.
  const TriangleMesh outer = icosphere(2, 1.0);
  const TriangleMesh inner = icosphere(2, 0.5);
  TriangleMesh m;
  m.V.resize(outer.V.rows() + inner.V.rows(), 3);
  m.V << outer.V, inner.V;
  m.F.resize(outer.F.rows() + inner.F.rows(), 3);
  m.F << outer.F, inner.F.array() + static_cast<int>(outer.V.rows());
  RepairReport report;
  const TriangleMesh out = validate_and_repair(m, "shell", {.require_closed = true}, &report);
  EXPECT_EQ(report.components, 2u);
  EXPECT_EQ(report.inward_faces_reversed, static_cast<std::size_t>(inner.F.rows()));
  EXPECT_EQ(report.faces_reoriented, 0u);
  EXPECT_NEAR(signed_volume(out), signed_volume(outer) - signed_volume(inner), 1e-12);
  for (Eigen::Index f = outer.F.rows(); f < out.F.rows(); ++f) {
    EXPECT_LT(normal(out, f).dot(centroid(out, f)), 0.0) << "inner face " << f;
  }
}

TEST(MeshRepair, OverlappingInwardCubesAreReversedOneByOne) {
  // Two inward cubes overlapping by half: closed but self-intersecting, so each closed
  // component is oriented on its own (there is no single volume to bound).
  TriangleMesh m;
  const TriangleMesh c = cube();
  m.V.resize(16, 3);
  m.V << c.V, c.V.rowwise() + Eigen::RowVector3d(0.5, 0.5, 0.5);
  m.F.resize(24, 3);
  m.F << c.F, c.F.array() + 8;
  m.F.col(1).swap(m.F.col(2));
  RepairReport report;
  const TriangleMesh out =
      validate_and_repair(m, "overlap", {.reject_self_intersections = false}, &report);
  EXPECT_GT(report.self_intersecting_pairs, 0u);
  EXPECT_EQ(report.components, 2u);
  EXPECT_TRUE(report.closed);
  EXPECT_EQ(report.inward_faces_reversed, 24u);
  EXPECT_EQ(report.faces_reoriented, 0u);
  TriangleMesh first = out, second = out;
  first.F = out.F.topRows(12);
  second.F = out.F.bottomRows(12);
  EXPECT_TRUE(faces_point_away_from(first, kCubeCentre));
  EXPECT_TRUE(faces_point_away_from(second, kCubeCentre + Eigen::Vector3d::Constant(0.5)));
}

// ---------------------------------------------------------------------------------------------
// validate_and_repair on the files of tests/data/broken_meshes, through load_mesh

TEST(MeshRepair, DegenerateFaceFileIsRepaired) {
  RepairReport report;
  const TriangleMesh out = repair_file("degenerate_face.obj", report, {.require_closed = true});
  EXPECT_EQ(report.degenerate_faces_removed, 1u);
  EXPECT_EQ(report.duplicate_faces_removed, 0u);
  EXPECT_EQ(report.faces_reoriented, 0u);
  EXPECT_EQ(report.edges_stitched, 0u);
  EXPECT_EQ(report.repairs, std::vector<std::string>{"removed 1 degenerate face (zero area)"});
  EXPECT_TRUE(report.closed);
  // The edge flip turns the sliver and its neighbour into two proper triangles.
  EXPECT_EQ(out.F.rows(), 14);
  EXPECT_GT(min_face_area(out), 0.1);
  EXPECT_NEAR(mpmgeom::surface_area(out), 6.0, 1e-6);
  EXPECT_NEAR(signed_volume(out), 1.0, 1e-6);
  EXPECT_TRUE(faces_point_away_from(out, kCubeCentre));
}

TEST(MeshRepair, FacesRebuiltAroundADegenerateFaceKeepTheirPart) {
  // The sliver belongs to the top part, its neighbour across the flipped edge to the side part:
  // both triangles that replace them lie in the side y = 0 and must carry the side's part.
  TriangleMesh m = load_mesh(kBroken / "degenerate_face.obj");
  m.part_names = {"sides", "top"};
  for (Eigen::Index f = 0; f < m.F.rows(); ++f) {
    const bool sliver = std::abs(normal(m, f).norm()) < 1e-12;
    m.part(f) = sliver || centroid(m, f).z() > 1.0 - 1e-9 ? 1 : 0;
  }
  RepairReport report;
  const TriangleMesh out = validate_and_repair(m, "two parts", {}, &report);
  ASSERT_EQ(report.degenerate_faces_removed, 1u);
  for (Eigen::Index f = 0; f < out.F.rows(); ++f) {
    const bool top = std::abs(normal(out, f).normalized().z() - 1.0) < 1e-9;
    EXPECT_EQ(out.part(f), top ? 1 : 0) << "face " << f << " at " << centroid(out, f).transpose();
  }
}

TEST(MeshRepair, DuplicateFaceFileIsRepaired) {
  RepairReport report;
  const TriangleMesh out = repair_file("duplicate_face.obj", report, {.require_closed = true});
  EXPECT_EQ(report.duplicate_faces_removed, 1u);
  EXPECT_EQ(report.degenerate_faces_removed, 0u);
  EXPECT_EQ(report.faces_reoriented, 0u);
  EXPECT_EQ(report.repairs, std::vector<std::string>{"removed 1 duplicate face"});
  EXPECT_TRUE(report.closed);
  EXPECT_EQ(out.F.rows(), 12);
  EXPECT_NEAR(signed_volume(out), 1.0, 1e-6);
}

TEST(MeshRepair, FlippedFaceFileIsReoriented) {
  RepairReport report;
  const TriangleMesh out = repair_file("flipped_face.obj", report, {.require_closed = true});
  EXPECT_EQ(report.faces_reoriented, 1u);
  EXPECT_EQ(report.inward_faces_reversed, 0u);
  EXPECT_EQ(report.repairs,
            std::vector<std::string>{"flipped 1 face to agree with their neighbours"});
  EXPECT_TRUE(report.closed);
  EXPECT_TRUE(report.outward);
  EXPECT_EQ(out.F.rows(), 12);
  EXPECT_TRUE(faces_point_away_from(out, kCubeCentre));
}

TEST(MeshRepair, InwardCubeFileIsReversed) {
  RepairReport report;
  const TriangleMesh out = repair_file("inward_cube.obj", report, {.require_closed = true});
  EXPECT_EQ(report.inward_faces_reversed, 12u);
  EXPECT_EQ(report.faces_reoriented, 0u);
  ASSERT_EQ(report.repairs.size(), 1u);
  EXPECT_TRUE(
      contains(report.repairs[0], "reversed 1 closed surface (12 faces) that faced inward"));
  EXPECT_TRUE(report.closed);
  EXPECT_TRUE(report.outward);
  EXPECT_NEAR(signed_volume(out), 1.0, 1e-6);
  EXPECT_TRUE(faces_point_away_from(out, kCubeCentre));
}

TEST(MeshRepair, SplitSeamFileIsStitched) {
  const fs::path file = kBroken / "split_seam.obj";
  const TriangleMesh loaded = load_mesh(file);
  ASSERT_EQ(loaded.V.rows(), 12) << "the importer must not weld the seam, or this tests nothing";
  RepairReport report;
  const TriangleMesh out =
      validate_and_repair(loaded, file.string(), {.require_closed = true}, &report);
  EXPECT_EQ(report.edges_stitched, 4u);
  EXPECT_EQ(report.degenerate_faces_removed, 0u);
  EXPECT_EQ(report.repairs.size(), 1u);
  EXPECT_TRUE(report.closed);
  EXPECT_EQ(report.components, 1u);
  EXPECT_EQ(out.V.rows(), 8);
  EXPECT_EQ(out.F.rows(), 12);
  EXPECT_NEAR(signed_volume(out), 1.0, 1e-6);
}

TEST(MeshRepair, OpenBoxFileIsAnErrorOnlyWhereClosedIsRequired) {
  EXPECT_TRUE(contains(error_of_file("open_box.obj", {.require_closed = true}),
                       "open_box.obj': open surface (4 border edges) where a closed surface is "
                       "required"));
  RepairReport report;
  const TriangleMesh out = repair_file("open_box.obj", report);
  expect_nothing_repaired(report);
  EXPECT_FALSE(report.closed);
  EXPECT_EQ(report.border_edges, 4u);
  EXPECT_EQ(report.components, 1u);
  EXPECT_EQ(out.F.rows(), 10);
  EXPECT_TRUE(faces_point_away_from(out, kCubeCentre));  // kept as it came
}

TEST(MeshRepair, NonManifoldEdgeFileIsRejected) {
  const std::string message = error_of_file("non_manifold_edge.obj");
  EXPECT_TRUE(
      contains(message, "non_manifold_edge.obj': 1 non-manifold edge (first at (0.5, 0, 0)"));
  EXPECT_TRUE(contains(message, "shared by 3 faces"));
}

TEST(MeshRepair, SelfIntersectingFileIsRejectedUnlessAllowed) {
  EXPECT_TRUE(contains(error_of_file("self_intersecting.obj"),
                       "self_intersecting.obj': 1 pair of self-intersecting faces (first: faces 0 "
                       "and 1)"));
  RepairReport report;
  const TriangleMesh out =
      repair_file("self_intersecting.obj", report, {.reject_self_intersections = false});
  EXPECT_EQ(report.self_intersecting_pairs, 1u);
  EXPECT_EQ(report.components, 2u);
  EXPECT_EQ(report.border_edges, 6u);
  EXPECT_FALSE(report.closed);
  EXPECT_EQ(out.F.rows(), 2);
}

TEST(MeshRepair, NanVertexFileIsRejected) {
  // The importer already refuses it, naming the file and the vertex.
  const std::string message = error_of_file("nan_vertex.obj");
  EXPECT_TRUE(contains(message, "nan_vertex.obj'"));
  EXPECT_TRUE(contains(message, "non-finite coordinate"));
}

// ---------------------------------------------------------------------------------------------
// remesh_isotropic

TEST(MeshRepair, RemeshedSphereHasTargetEdgeLength) {
  const TriangleMesh sphere = icosphere(3);  // edges about 0.13
  const double target = 0.1;
  const TriangleMesh out = remesh_isotropic(sphere, target, 5);
  // CGAL splits edges above 4/3 and collapses edges below 4/5 of the target.
  EXPECT_NEAR(mean_edge_length(out), target, 0.2 * target);
  EXPECT_NEAR(mpmgeom::surface_area(out), mpmgeom::surface_area(sphere),
              0.02 * mpmgeom::surface_area(sphere));
  RepairReport report;
  validate_and_repair(out, "remeshed sphere", {.require_closed = true}, &report);
  expect_nothing_repaired(report);
  EXPECT_TRUE(report.closed);
  EXPECT_EQ(report.components, 1u);
  EXPECT_EQ(report.self_intersecting_pairs, 0u);
  EXPECT_GT(signed_volume(out), 0.0);
  EXPECT_EQ(out.part_names, sphere.part_names);
}

TEST(MeshRepair, RemeshKeepsPartsAndTheBoundaryBetweenThem) {
  const TriangleMesh plane = grid_plane(4);  // cells 0.25, parts split at x = 0.5
  const TriangleMesh out = remesh_isotropic(plane, 0.1, 5);
  ASSERT_GT(out.F.rows(), plane.F.rows());
  EXPECT_EQ(out.part_names, plane.part_names);
  std::array<double, 2> area{0.0, 0.0};
  for (Eigen::Index f = 0; f < out.F.rows(); ++f) {
    ASSERT_TRUE(out.part(f) == 0 || out.part(f) == 1);
    area[static_cast<std::size_t>(out.part(f))] += 0.5 * normal(out, f).norm();
    EXPECT_EQ(centroid(out, f).x() < 0.5, out.part(f) == 0) << "face " << f;
    EXPECT_GT(normal(out, f).z(), 0.0);
  }
  // Both parts keep their exact area: the boundary x = 0.5 and the border did not move.
  EXPECT_NEAR(area[0], 0.5, 1e-12);
  EXPECT_NEAR(area[1], 0.5, 1e-12);
  std::size_t boundary_edges = 0;
  for (const auto& [e, faces] : edges(out)) {
    if (faces.size() == 2 && out.part(faces[0]) != out.part(faces[1])) {
      ++boundary_edges;
      EXPECT_NEAR(out.V(e.first, 0), 0.5, 1e-12);
      EXPECT_NEAR(out.V(e.second, 0), 0.5, 1e-12);
    }
  }
  EXPECT_GE(boundary_edges, 8u);  // the unit-long boundary at about 0.1 per edge
  EXPECT_NEAR(mean_edge_length(out), 0.1, 0.02);
}

TEST(MeshRepair, CoarseningKeepsTheCornersOfABorder) {
  // Coarsening collapses border edges along the border; the square's corners must stay.
  const TriangleMesh plane = grid_plane(8);  // cells 0.125
  const TriangleMesh out = remesh_isotropic(plane, 0.4, 5);
  ASSERT_LT(out.F.rows(), plane.F.rows());
  EXPECT_NEAR(mpmgeom::surface_area(out), 1.0, 1e-12);
  for (const Eigen::Vector3d& corner_point : {Eigen::Vector3d(0, 0, 0), Eigen::Vector3d(1, 0, 0),
                                              Eigen::Vector3d(1, 1, 0), Eigen::Vector3d(0, 1, 0)}) {
    EXPECT_TRUE((out.V.rowwise() - corner_point.transpose()).rowwise().norm().minCoeff() < 1e-12)
        << corner_point.transpose();
  }
  EXPECT_NEAR(mean_edge_length(out), 0.4, 0.2 * 0.4);
}

TEST(MeshRepair, RemeshKeepsSharpEdgesOfACube) {
  const TriangleMesh out = remesh_isotropic(cube(), 0.2, 5);
  EXPECT_GT(out.F.rows(), 12);
  EXPECT_NEAR(mpmgeom::surface_area(out), 6.0, 1e-9);
  EXPECT_NEAR(signed_volume(out), 1.0, 1e-9);
  for (Eigen::Index v = 0; v < out.V.rows(); ++v) {
    const Eigen::Array3d p = out.V.row(v).transpose();
    EXPECT_TRUE((p.abs() < 1e-12).any() || ((p - 1.0).abs() < 1e-12).any()) << p.transpose();
  }
  const auto box = mpmgeom::bounding_box(out);
  EXPECT_TRUE(box.min().isZero(1e-12));
  EXPECT_TRUE(box.max().isOnes(1e-12));
}

TEST(MeshRepair, RemeshRejectsBadArguments) {
  const TriangleMesh c = cube();
  EXPECT_THROW(remesh_isotropic(c, 0.0), std::invalid_argument);
  EXPECT_THROW(remesh_isotropic(c, -0.1), std::invalid_argument);
  EXPECT_THROW(remesh_isotropic(c, std::numeric_limits<double>::quiet_NaN()),
               std::invalid_argument);
  EXPECT_THROW(remesh_isotropic(c, 0.1, 0), std::invalid_argument);
  EXPECT_THROW(remesh_isotropic(c, 0.1, 3, 0.0), std::invalid_argument);
  EXPECT_THROW(remesh_isotropic(c, 0.1, 3, 180.0), std::invalid_argument);
  TriangleMesh flipped = c;
  flipped.F.row(0) << 0, 2, 3;  // inconsistent orientation: repair first
  EXPECT_THROW(remesh_isotropic(flipped, 0.1), MeshError);
}

}  // namespace
