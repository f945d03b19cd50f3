// Tests for mpmgeom::load_mesh / save_mesh: the shipped cube, placement options, round trips
// through every writer, and the defects that must be rejected with a one-line MeshError.

#include "mpmgeom/triangle_mesh.hpp"

#include <gtest/gtest.h>

#include <unistd.h>

#include <array>
#include <cmath>
#include <cstdint>
#include <filesystem>
#include <fstream>
#include <functional>
#include <limits>
#include <random>
#include <sstream>
#include <string>
#include <vector>

namespace {

namespace fs = std::filesystem;
using mpmgeom::ImportOptions;
using mpmgeom::ImportReport;
using mpmgeom::load_mesh;
using mpmgeom::MeshError;
using mpmgeom::save_mesh;
using mpmgeom::TriangleMesh;

const fs::path kCube = fs::path(MPM_DATA_DIR) / "meshes" / "unit_cube.obj";

// A directory of its own per test: ctest runs the tests of this file as parallel processes.
class ScratchDir {
 public:
  ScratchDir() {
    const auto* info = ::testing::UnitTest::GetInstance()->current_test_info();
    path_ = fs::temp_directory_path() /
            ("mpmgeom_" + std::string(info->name()) + "_" + std::to_string(::getpid()));
    fs::remove_all(path_);
    fs::create_directories(path_);
  }
  ~ScratchDir() {
    std::error_code ec;
    fs::remove_all(path_, ec);
  }
  ScratchDir(const ScratchDir&) = delete;
  ScratchDir& operator=(const ScratchDir&) = delete;
  fs::path operator/(const std::string& name) const { return path_ / name; }

 private:
  fs::path path_;
};

void write_text(const fs::path& file, const std::string& text) {
  std::ofstream out(file, std::ios::binary);
  out << text;
  ASSERT_TRUE(out.good()) << file;
}

// Runs `load`, expects a MeshError and returns its message.
std::string error_of(const std::function<void()>& load) {
  try {
    load();
  } catch (const MeshError& e) {
    return e.what();
  }
  ADD_FAILURE() << "expected a MeshError";
  return {};
}

// Six times the enclosed volume is positive iff the faces point outwards.
double signed_volume(const TriangleMesh& m) {
  double six_v = 0.0;
  for (Eigen::Index f = 0; f < m.F.rows(); ++f) {
    const Eigen::Vector3d a = m.V.row(m.F(f, 0));
    const Eigen::Vector3d b = m.V.row(m.F(f, 1));
    const Eigen::Vector3d c = m.V.row(m.F(f, 2));
    six_v += a.dot(b.cross(c));
  }
  return six_v / 6.0;
}

void expect_box(const Eigen::AlignedBox3d& box, const Eigen::Vector3d& lo,
                const Eigen::Vector3d& hi, double tol = 1e-6) {
  EXPECT_TRUE(box.min().isApprox(lo, tol) || (box.min() - lo).norm() < tol)
      << "min " << box.min().transpose() << " expected " << lo.transpose();
  EXPECT_TRUE(box.max().isApprox(hi, tol) || (box.max() - hi).norm() < tol)
      << "max " << box.max().transpose() << " expected " << hi.transpose();
}

// Same triangles with the same orientation, in any order and any vertex numbering: every face of
// `a` must match a distinct face of `b` up to a cyclic shift of its corners.
void expect_same_surface(const TriangleMesh& a, const TriangleMesh& b, double tol) {
  ASSERT_EQ(a.F.rows(), b.F.rows());
  std::vector<bool> taken(static_cast<std::size_t>(b.F.rows()), false);
  for (Eigen::Index fa = 0; fa < a.F.rows(); ++fa) {
    bool matched = false;
    for (Eigen::Index fb = 0; fb < b.F.rows() && !matched; ++fb) {
      if (taken[static_cast<std::size_t>(fb)]) continue;
      for (int shift = 0; shift < 3 && !matched; ++shift) {
        bool all = true;
        for (int k = 0; k < 3 && all; ++k) {
          const Eigen::Vector3d pa = a.V.row(a.F(fa, k));
          const Eigen::Vector3d pb = b.V.row(b.F(fb, (k + shift) % 3));
          all = (pa - pb).norm() <= tol;
        }
        if (all) matched = taken[static_cast<std::size_t>(fb)] = true;
      }
    }
    EXPECT_TRUE(matched) << "face " << fa << " has no counterpart";
  }
}

std::string ascii_stl(const std::string& name,
                      const std::vector<std::array<std::string, 3>>& tris) {
  std::string s = "solid " + name + "\n";
  for (const auto& t : tris) {
    s += "  facet normal 0 0 1\n    outer loop\n";
    for (const auto& v : t) s += "      vertex " + v + "\n";
    s += "    endloop\n  endfacet\n";
  }
  return s + "endsolid " + name + "\n";
}

TEST(MeshImport, LoadsShippedCube) {
  ImportReport report;
  const TriangleMesh m = load_mesh(kCube, {}, &report);
  EXPECT_EQ(m.F.rows(), 12);
  EXPECT_EQ(m.V.rows(), 8);
  ASSERT_EQ(m.part.size(), 12);
  EXPECT_TRUE((m.part.array() == 0).all());
  EXPECT_EQ(m.part_names, std::vector<std::string>{"cube"});
  EXPECT_NEAR(mpmgeom::surface_area(m), 6.0, 1e-12);
  EXPECT_NEAR(signed_volume(m), 1.0, 1e-12);  // counter-clockwise from outside
  expect_box(mpmgeom::bounding_box(m), Eigen::Vector3d::Zero(), Eigen::Vector3d::Ones(), 1e-12);
  EXPECT_GE(m.F.minCoeff(), 0);
  EXPECT_LT(m.F.maxCoeff(), 8);

  EXPECT_EQ(report.input_triangles, 12u);
  EXPECT_EQ(report.skipped_primitives, 0u);
  EXPECT_EQ(report.dropped_degenerate_faces, 0u);
  EXPECT_NEAR(report.weld_tolerance, 1e-9 * std::sqrt(3.0), 1e-15);
}

TEST(MeshImport, ScaleRotateTranslateMoveTheBox) {
  ImportOptions o;
  o.scale = 2.0;
  o.rotation_deg = {0.0, 0.0, 90.0};  // (x, y) -> (-y, x)
  o.translation = {1.0, 2.0, 3.0};
  const TriangleMesh m = load_mesh(kCube, o);
  expect_box(mpmgeom::bounding_box(m), {-1.0, 2.0, 3.0}, {1.0, 4.0, 5.0});
  EXPECT_NEAR(mpmgeom::surface_area(m), 24.0, 1e-9);
  EXPECT_NEAR(signed_volume(m), 8.0, 1e-9);  // a proper rotation keeps the faces outwards
}

TEST(MeshImport, RotationsApplyXThenYThenZ) {
  // x first: (x, y, z) -> (x, -z, y) gives [0,1]x[-1,0]x[0,1]; then y: (x, y, z) -> (z, y, -x)
  // gives [0,1]x[-1,0]x[-1,0]. The other order would end in [0,1]^3.
  ImportOptions o;
  o.rotation_deg = {90.0, 90.0, 0.0};
  expect_box(mpmgeom::bounding_box(load_mesh(kCube, o)), {0.0, -1.0, -1.0}, {1.0, 0.0, 0.0});

  o.rotation_deg = {0.0, 90.0, 90.0};  // y: [0,1]^2x[-1,0]; then z: (x,y)->(-y,x)
  expect_box(mpmgeom::bounding_box(load_mesh(kCube, o)), {-1.0, 0.0, -1.0}, {0.0, 1.0, 0.0});
}

TEST(MeshImport, RejectsInvalidOptions) {
  const double nan = std::numeric_limits<double>::quiet_NaN();
  const double inf = std::numeric_limits<double>::infinity();
  std::vector<std::function<void(ImportOptions&)>> breakers = {
      [](ImportOptions& o) { o.scale = 0.0; },
      [](ImportOptions& o) { o.scale = -1.0; },
      [=](ImportOptions& o) { o.scale = nan; },
      [=](ImportOptions& o) { o.scale = inf; },
      [=](ImportOptions& o) { o.translation.y() = nan; },
      [=](ImportOptions& o) { o.rotation_deg.z() = inf; },
      [](ImportOptions& o) { o.weld_tolerance = -1e-3; },
      [=](ImportOptions& o) { o.weld_tolerance = inf; },
  };
  EXPECT_TRUE(ImportOptions{}.valid(nullptr));
  for (std::size_t i = 0; i < breakers.size(); ++i) {
    SCOPED_TRACE(i);
    ImportOptions o;
    breakers[i](o);
    std::string why;
    EXPECT_FALSE(o.valid(&why));
    EXPECT_FALSE(why.empty());
    const std::string msg = error_of([&] { load_mesh(kCube, o); });
    EXPECT_NE(msg.find("unit_cube.obj"), std::string::npos) << msg;
    EXPECT_NE(msg.find(why), std::string::npos) << msg;
  }
}

// Saves the cube in a pose whose coordinates are not exactly representable, reloads it and
// compares face by face; float storage in assimp bounds the error.
void round_trip(const std::string& file_name, bool binary) {
  ScratchDir dir;
  ImportOptions o;
  o.rotation_deg = {10.0, 20.0, 30.0};
  o.translation = {-0.25, 3.5, 100.0};
  const TriangleMesh original = load_mesh(kCube, o);
  const fs::path file = dir / file_name;
  save_mesh(original, file, {.binary = binary});
  ASSERT_TRUE(fs::exists(file));
  const TriangleMesh back = load_mesh(file);
  EXPECT_EQ(back.V.rows(), 8);
  EXPECT_EQ(back.F.rows(), 12);
  EXPECT_NEAR(mpmgeom::surface_area(back), 6.0, 1e-4);
  EXPECT_NEAR(signed_volume(back), 1.0, 1e-4);
  expect_same_surface(original, back, 1e-4);
}

TEST(MeshImport, RoundTripsBinaryStl) { round_trip("cube.stl", true); }
TEST(MeshImport, RoundTripsAsciiStl) { round_trip("cube.stl", false); }
TEST(MeshImport, RoundTripsObj) { round_trip("cube.obj", false); }
TEST(MeshImport, RoundTripsBinaryPly) { round_trip("cube.ply", true); }

TEST(MeshImport, SavedStlIsBinaryOrAsciiAsAsked) {
  ScratchDir dir;
  const TriangleMesh cube = load_mesh(kCube);
  save_mesh(cube, dir / "b.stl", {.binary = true});
  save_mesh(cube, dir / "a.stl", {.binary = false});
  EXPECT_EQ(fs::file_size(dir / "b.stl"), 84u + 50u * 12u);
  std::ifstream in(dir / "a.stl");
  std::string first;
  in >> first;
  EXPECT_EQ(first, "solid");
}

// Facet normals and corner order of an STL file, read without assimp.
struct StlFacet {
  Eigen::Vector3d normal;
  std::array<Eigen::Vector3d, 3> corners;
};

std::vector<StlFacet> read_stl_facets(const fs::path& file, bool binary) {
  std::vector<StlFacet> facets;
  std::ifstream in(file, std::ios::binary);
  if (binary) {
    in.seekg(80);
    std::uint32_t count = 0;
    in.read(reinterpret_cast<char*>(&count), 4);
    for (std::uint32_t t = 0; t < count; ++t) {
      std::array<float, 12> v{};
      in.read(reinterpret_cast<char*>(v.data()), 48);
      in.ignore(2);
      StlFacet f;
      f.normal = {v[0], v[1], v[2]};
      for (int k = 0; k < 3; ++k) f.corners[k] = {v[3 + 3 * k], v[4 + 3 * k], v[5 + 3 * k]};
      facets.push_back(f);
    }
  } else {
    std::string word;
    while (in >> word) {
      if (word == "normal") {
        facets.emplace_back();
        in >> facets.back().normal.x() >> facets.back().normal.y() >> facets.back().normal.z();
        in >> word >> word;  // "outer loop"
        for (auto& c : facets.back().corners) in >> word >> c.x() >> c.y() >> c.z();
      }
    }
  }
  return facets;
}

TEST(MeshImport, SavedStlNormalsMatchTheWinding) {
  ScratchDir dir;
  ImportOptions o;
  o.rotation_deg = {10.0, 20.0, 30.0};
  const TriangleMesh cube = load_mesh(kCube, o);
  for (const bool binary : {true, false}) {
    SCOPED_TRACE(binary ? "binary" : "ascii");
    const fs::path file = dir / (binary ? "b.stl" : "a.stl");
    save_mesh(cube, file, {.binary = binary});
    const std::vector<StlFacet> facets = read_stl_facets(file, binary);
    ASSERT_EQ(facets.size(), 12u);
    for (const StlFacet& f : facets) {
      const Eigen::Vector3d n =
          (f.corners[1] - f.corners[0]).cross(f.corners[2] - f.corners[0]).normalized();
      EXPECT_NEAR(f.normal.dot(n), 1.0, 1e-5) << f.normal.transpose() << " vs " << n.transpose();
    }
  }
}

TEST(MeshImport, TwoObjObjectsKeepTheirNames) {
  ScratchDir dir;
  // Two unit quads sharing the edge x = 1; quads exercise triangulation, the shared edge the weld
  // across parts.
  write_text(dir / "two.obj",
             "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nv 2 0 0\nv 2 1 0\n"
             "o left\nf 1 2 3 4\n"
             "o right\nf 2 5 6 3\n");
  const TriangleMesh m = load_mesh(dir / "two.obj");
  EXPECT_EQ(m.part_names, (std::vector<std::string>{"left", "right"}));
  EXPECT_EQ(m.F.rows(), 4);
  EXPECT_EQ(m.V.rows(), 6);
  ASSERT_EQ(m.part.size(), 4);
  EXPECT_EQ((m.part.array() == 0).count(), 2);
  EXPECT_EQ((m.part.array() == 1).count(), 2);
  EXPECT_NEAR(mpmgeom::surface_area(m), 2.0, 1e-12);
  for (Eigen::Index f = 0; f < m.F.rows(); ++f) {
    const Eigen::Vector3d c = (m.V.row(m.F(f, 0)) + m.V.row(m.F(f, 1)) + m.V.row(m.F(f, 2))) / 3;
    EXPECT_EQ(m.part(f), c.x() < 1.0 ? 0 : 1) << "face " << f;
  }
}

TEST(MeshImport, ObjRoundTripKeepsPartNames) {
  ScratchDir dir;
  write_text(dir / "two.obj",
             "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nv 2 0 0\nv 2 1 0\n"
             "o left\nf 1 2 3 4\n"
             "o right\nf 2 5 6 3\n");
  const TriangleMesh m = load_mesh(dir / "two.obj");
  save_mesh(m, dir / "again.obj");
  const TriangleMesh back = load_mesh(dir / "again.obj");
  EXPECT_EQ(back.part_names, m.part_names);
  EXPECT_EQ(back.V.rows(), 6);
  expect_same_surface(m, back, 1e-6);
}

TEST(MeshImport, TruncatedBinaryStlThrowsWithFileName) {
  ScratchDir dir;
  const fs::path file = dir / "truncated_wall.stl";
  {
    std::ofstream out(file, std::ios::binary);
    std::string header = "binary STL cut short";
    header.resize(80, ' ');
    out.write(header.data(), 80);
    const std::uint32_t announced = 100;  // little-endian on every platform we build for
    out.write(reinterpret_cast<const char*>(&announced), 4);
    const std::array<float, 12> facet{0, 0, 1, 0, 0, 0, 1, 0, 0, 0, 1, 0};
    for (int t = 0; t < 2; ++t) {
      out.write(reinterpret_cast<const char*>(facet.data()), 48);
      out.write("\0\0", 2);
    }
  }
  ASSERT_EQ(fs::file_size(file), 84u + 2u * 50u);
  const std::string msg = error_of([&] { load_mesh(file); });
  EXPECT_NE(msg.find(file.string()), std::string::npos) << msg;
  EXPECT_NE(msg.find("100 triangles"), std::string::npos) << msg;
  EXPECT_EQ(msg.find('\n'), std::string::npos) << msg;
}

TEST(MeshImport, MissingFileThrowsWithFileName) {
  const fs::path file = fs::path(MPM_DATA_DIR) / "meshes" / "no_such_wall.stl";
  const std::string msg = error_of([&] { load_mesh(file); });
  EXPECT_EQ(msg, "mesh '" + file.string() + "': file does not exist");
}

TEST(MeshImport, FaceWithoutVerticesThrowsInsteadOfAborting) {
  // assimp 5.2 parses this garbled PLY with an empty face, validates it, and then aborts the
  // whole process in its triangulation; load_mesh must refuse it before that (found by fuzzing).
  const fs::path file = fs::path(MPM_DATA_DIR) / ".." / "tests" / "data" / "broken_meshes" /
                        "face_without_vertices.ply";
  const std::string msg = error_of([&] { load_mesh(file); });
  EXPECT_EQ(msg, "mesh '" + file.string() + "': face 9 has no vertices (a malformed file)");
}

TEST(MeshImport, PlyHeadersAssimpLoopsOnThrow) {
  // assimp 5.2 never returns from these (found by fuzzing): refused before it sees them.
  const fs::path dir = fs::temp_directory_path() / ("mpm_ply_" + std::to_string(::getpid()));
  fs::create_directories(dir);
  const auto write = [&](const std::string& name, const std::string& text) {
    std::ofstream(dir / name) << text;
    return dir / name;
  };
  const fs::path unended =
      write("unended.ply", "ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\n0\n");
  EXPECT_EQ(error_of([&] { load_mesh(unended); }),
            "mesh '" + unended.string() +
                "': PLY header line 5 ('0') is not a header line and no end_header came before it "
                "(a malformed or truncated file)");
  const fs::path endless =
      write("endless.ply", "ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\n");
  EXPECT_EQ(error_of([&] { load_mesh(endless); }),
            "mesh '" + endless.string() +
                "': PLY header has no end_header line (a malformed or truncated file)");
  // The magic number in mixed case, which assimp accepts (found by fuzzing: it looped on this).
  const fs::path mixed = write(
      "mixed.ply", "plY\nformat ascii 1.0\nelement vertex 1\nproperty float x\nend_?header\n");
  EXPECT_EQ(error_of([&] { load_mesh(mixed); }),
            "mesh '" + mixed.string() +
                "': PLY header line 5 ('end_?header') is not a header line and no end_header came "
                "before it (a malformed or truncated file)");
  const fs::path uncounted =
      write("uncounted.ply", "ply\nformat ascii 1.0\nelement vertex\nend_header\n");
  EXPECT_EQ(error_of([&] { load_mesh(uncounted); }),
            "mesh '" + uncounted.string() +
                "': PLY header line 3 is not 'element <name> <count>' (a malformed file)");
  // An element name that starts with digits: assimp parses it as the count (found by fuzzing:
  // "element 666...6vertex 8" made it ask for 64 GiB).
  const fs::path numeric = write("numeric.ply",
                                 "ply\nformat ascii 1.0\nelement 6666666666vertex 8\n"
                                 "property float x\nend_header\n");
  EXPECT_EQ(error_of([&] { load_mesh(numeric); }),
            "mesh '" + numeric.string() +
                "': PLY header line 3 is not 'element <name> <count>' (a malformed file)");
  // A property of no known type, or before any element.
  const fs::path untyped = write("untyped.ply",
                                 "ply\nformat ascii 1.0\nelement vertex 8\n"
                                 "property flaot x\nend_header\n");
  const std::string property_rule =
      "' or 'property list <type> <type> <name>' after an 'element' (a malformed file)";
  EXPECT_EQ(error_of([&] { load_mesh(untyped); }),
            "mesh '" + untyped.string() + "': PLY header line 4 is not 'property <type> <name>" +
                property_rule);
  const fs::path orphan =
      write("orphan.ply", "ply\nformat ascii 1.0\nproperty float x\nend_header\n");
  EXPECT_EQ(error_of([&] { load_mesh(orphan); }),
            "mesh '" + orphan.string() + "': PLY header line 3 is not 'property <type> <name>" +
                property_rule);
  // Comments, obj_info and blank lines are header lines.
  const fs::path commented = write("commented.ply",
                                   "ply\nformat ascii 1.0\ncomment made by hand\nobj_info x\n\n"
                                   "element vertex 3\nproperty float x\nproperty float y\n"
                                   "property float z\nelement face 1\n"
                                   "property list uchar int vertex_indices\nend_header\n"
                                   "0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n");
  EXPECT_EQ(load_mesh(commented).F.rows(), 1);
  fs::remove_all(dir);
}

TEST(MeshImport, PlyCountsBeyondTheFileThrow) {
  // Found by fuzzing: a header announcing 37 digits of faces, for which assimp reserves memory.
  const fs::path file =
      fs::temp_directory_path() / ("mpm_ply_count_" + std::to_string(::getpid()) + ".ply");
  std::ofstream(file) << "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\n"
                         "property float y\nproperty float z\n"
                         "element face 3333333333333333333333333333333333388\n"
                         "property list uchar int vertex_indices\nend_header\n"
                         "0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n";
  EXPECT_EQ(error_of([&] { load_mesh(file); }),
            "mesh '" + file.string() +
                "': PLY header line 7 announces 3333333333333333333333333333333333388 'face' "
                "elements, more than the file's " +
                std::to_string(fs::file_size(file)) + " bytes can hold (a malformed file)");
  fs::remove(file);
  // The fuzzer's own input: its header is garbled before the count.
  const fs::path found =
      fs::path(MPM_DATA_DIR) / ".." / "tests" / "data" / "broken_meshes" / "huge_element_count.ply";
  EXPECT_EQ(error_of([&] { load_mesh(found); }),
            "mesh '" + found.string() +
                "': PLY header line 4 is not 'property <type> <name>' or 'property list <type> "
                "<type> <name>' after an 'element' (a malformed file)");
}

TEST(MeshImport, RunawayReaderIsStoppedAtItsMemoryBudget) {
  // Found by fuzzing: an ASCII PLY face announcing 3.4e41 indices, on which assimp 5.2 keeps
  // allocating (`mpm prep` grew to 24 GB until the kernel killed it). The reader runs in a child
  // process that is stopped at its budget; this process carries on. The budget is set here to
  // 256 MiB, which the child reaches in about a second of CPU time even under the sanitizer, far
  // from the 20 s CPU-time budget: with the default 4 GiB it took 14 s in the release build, and
  // under the sanitizer on a loaded machine the CPU-time budget was reached first.
  const fs::path file =
      fs::path(MPM_DATA_DIR) / ".." / "tests" / "data" / "broken_meshes" / "huge_list_count.ply";
  ImportOptions budget;
  budget.memory_budget_bytes = 256ull << 20;
  EXPECT_EQ(error_of([&] { load_mesh(file, budget); }),
            "mesh '" + file.string() +
                "': reading it took more than 256 MiB of memory (a malformed file announcing "
                "huge counts?); stopped");
  // The same process still reads a good mesh, in a child and in itself.
  EXPECT_EQ(load_mesh(kCube).F.rows(), 12);
  ImportOptions in_process;
  in_process.isolate = false;
  EXPECT_EQ(load_mesh(kCube, in_process).F.rows(), 12);
}

TEST(MeshImport, ChildAndInProcessReadersAgree) {
  // The soup crosses a pipe from the child: positions, faces, parts and the report must arrive
  // exactly as the in-process reader makes them.
  const fs::path file = fs::path(MPM_DATA_DIR) / "meshes" / "hillside_barrier.obj";
  ImportOptions options;
  options.rotation_deg = {10.0, -20.0, 30.0};
  options.scale = 2.0;
  ImportReport a, b;
  const TriangleMesh isolated = load_mesh(file, options, &a);
  options.isolate = false;
  const TriangleMesh local = load_mesh(file, options, &b);
  EXPECT_TRUE(isolated.V == local.V);
  EXPECT_TRUE(isolated.F == local.F);
  EXPECT_TRUE(isolated.part == local.part);
  EXPECT_EQ(isolated.part_names, local.part_names);
  EXPECT_GT(isolated.part_names.size(), 1u);
  EXPECT_EQ(a.input_vertices, b.input_vertices);
  EXPECT_EQ(a.input_triangles, b.input_triangles);
  EXPECT_EQ(a.skipped_primitives, b.skipped_primitives);
  EXPECT_EQ(a.dropped_degenerate_faces, b.dropped_degenerate_faces);
  EXPECT_EQ(a.weld_tolerance, b.weld_tolerance);
}

TEST(MeshImport, NonFiniteVertexInAsciiStlThrows) {
  ScratchDir dir;
  for (const std::string bad : {"nan", "inf"}) {
    SCOPED_TRACE(bad);
    const fs::path file = dir / ("bad_" + bad + ".stl");
    write_text(file,
               ascii_stl("bad", {{"0 0 0", "1 0 0", "0 1 0"}, {"1 0 0", bad + " 1 0", "0 1 0"}}));
    const std::string msg = error_of([&] { load_mesh(file); });
    EXPECT_NE(msg.find(file.string()), std::string::npos) << msg;
    EXPECT_NE(msg.find("non-finite"), std::string::npos) << msg;
    EXPECT_EQ(msg.find('\n'), std::string::npos) << msg;
  }
}

TEST(MeshImport, UnreadableFileThrows) {
  ScratchDir dir;
  const fs::path file = dir / "garbage.obj";
  write_text(file, "this is not a mesh\n\x01\x02\x03 at all {}\n");
  const std::string msg = error_of([&] { load_mesh(file); });
  EXPECT_NE(msg.find(file.string()), std::string::npos) << msg;
  EXPECT_EQ(msg.find('\n'), std::string::npos) << msg;
}

TEST(MeshImport, FileWithoutTrianglesThrows) {
  ScratchDir dir;
  const fs::path file = dir / "polyline.obj";
  write_text(file, "o wire\nv 0 0 0\nv 1 0 0\nv 1 1 0\nl 1 2 3\n");
  const std::string msg = error_of([&] { load_mesh(file); });
  EXPECT_NE(msg.find(file.string()), std::string::npos) << msg;
  EXPECT_NE(msg.find("no triangles"), std::string::npos) << msg;
}

TEST(MeshImport, WeldToleranceMergesNearbyVertices) {
  ScratchDir dir;
  // Two triangles of a unit square whose diagonal corners disagree by 1e-4.
  const fs::path file = dir / "gap.stl";
  write_text(
      file, ascii_stl("gap", {{"0 0 0", "1 0 0", "1 1 0"}, {"0.0001 0 0", "1 1.0001 0", "0 1 0"}}));
  EXPECT_EQ(load_mesh(file).V.rows(), 6);  // default tolerance: exact positions only

  ImportOptions o;
  o.weld_tolerance = 1e-3;
  ImportReport report;
  const TriangleMesh m = load_mesh(file, o, &report);
  EXPECT_EQ(m.V.rows(), 4);
  EXPECT_EQ(m.F.rows(), 2);
  EXPECT_EQ(report.weld_tolerance, 1e-3);
  EXPECT_EQ(report.dropped_degenerate_faces, 0u);

  // The tolerance is in output units: scaled by 1000, the gap is 0.1 and no longer welds.
  o.scale = 1000.0;
  EXPECT_EQ(load_mesh(file, o).V.rows(), 6);
}

TEST(MeshImport, WeldFindsNeighboursAcrossGridCells) {
  ScratchDir dir;
  // A 10 x 10 grid of squares (200 triangles, 121 corners) written as a triangle soup whose every
  // corner copy is jittered by up to 2e-4 per axis: with a 1e-3 tolerance each cluster must
  // collapse to one vertex, also the many clusters that straddle the welder's internal cells.
  std::mt19937 rng(12345);
  std::uniform_real_distribution<double> jitter(-2e-4, 2e-4);
  auto corner = [&](int i, int j) {
    std::ostringstream s;
    s.precision(17);
    s << 0.1 * i + jitter(rng) << ' ' << 0.1 * j + jitter(rng) << ' ' << jitter(rng);
    return s.str();
  };
  std::vector<std::array<std::string, 3>> tris;
  for (int i = 0; i < 10; ++i) {
    for (int j = 0; j < 10; ++j) {
      tris.push_back({corner(i, j), corner(i + 1, j), corner(i + 1, j + 1)});
      tris.push_back({corner(i, j), corner(i + 1, j + 1), corner(i, j + 1)});
    }
  }
  const fs::path file = dir / "jittered.stl";
  write_text(file, ascii_stl("grid", tris));
  ImportOptions o;
  o.weld_tolerance = 1e-3;
  ImportReport report;
  const TriangleMesh m = load_mesh(file, o, &report);
  EXPECT_EQ(report.input_vertices, 600u);
  EXPECT_EQ(m.V.rows(), 121);
  EXPECT_EQ(m.F.rows(), 200);
  EXPECT_EQ(report.dropped_degenerate_faces, 0u);
}

TEST(MeshImport, DegenerateFacesAreDroppedAndCounted) {
  ScratchDir dir;
  const fs::path file = dir / "sliver.stl";
  // The second triangle collapses once its first two corners weld.
  write_text(file,
             ascii_stl("sliver", {{"0 0 0", "1 0 0", "0 1 0"}, {"2 0 0", "2.00001 0 0", "2 1 0"}}));
  ImportOptions o;
  o.weld_tolerance = 1e-3;
  ImportReport report;
  const TriangleMesh m = load_mesh(file, o, &report);
  EXPECT_EQ(report.dropped_degenerate_faces, 1u);
  EXPECT_EQ(m.F.rows(), 1);
  EXPECT_EQ(m.V.rows(), 3);  // the sliver's vertices are not returned
  EXPECT_LT(m.V.col(0).maxCoeff(), 1.5);

  // Nothing left at all is an error, not an empty mesh.
  const fs::path only = dir / "only_sliver.stl";
  write_text(only, ascii_stl("s", {{"2 0 0", "2.00001 0 0", "2 1 0"}}));
  const std::string msg = error_of([&] { load_mesh(only, o); });
  EXPECT_NE(msg.find("degenerate"), std::string::npos) << msg;
}

TEST(MeshImport, GltfNodeTransformsApplyAndMirroringKeepsOrientation) {
  ScratchDir dir;
  // One triangle (0,0,0) (1,0,0) (0,1,0) with normal +z, instanced by a translated node and by a
  // node mirrored in x. The buffer is 3 float32 VEC3 positions and 3 uint16 indices (+ padding).
  const fs::path file = dir / "instances.gltf";
  write_text(file, R"({
  "asset": {"version": "2.0"},
  "scene": 0,
  "scenes": [{"nodes": [0, 1]}],
  "nodes": [{"name": "moved", "mesh": 0, "translation": [10, 0, 0]},
            {"name": "mirrored", "mesh": 0, "scale": [-1, 1, 1]}],
  "meshes": [{"name": "tri", "primitives": [{"attributes": {"POSITION": 0}, "indices": 1}]}],
  "buffers": [{"byteLength": 44,
    "uri": "data:application/octet-stream;base64,AAAAAAAAAAAAAAAAAACAPwAAAAAAAAAAAAAAAAAAgD8AAAAAAAABAAIAAAA="}],
  "bufferViews": [{"buffer": 0, "byteOffset": 0, "byteLength": 36},
                  {"buffer": 0, "byteOffset": 36, "byteLength": 6}],
  "accessors": [{"bufferView": 0, "componentType": 5126, "count": 3, "type": "VEC3",
                 "min": [0, 0, 0], "max": [1, 1, 0]},
                {"bufferView": 1, "componentType": 5123, "count": 3, "type": "SCALAR"}]
})");
  const TriangleMesh m = load_mesh(file);
  ASSERT_EQ(m.F.rows(), 2);
  EXPECT_EQ(m.V.rows(), 6);
  EXPECT_EQ(m.part_names, std::vector<std::string>{"tri"});
  expect_box(mpmgeom::bounding_box(m), {-1.0, 0.0, 0.0}, {11.0, 1.0, 0.0});
  for (Eigen::Index f = 0; f < 2; ++f) {
    const Eigen::Vector3d a = m.V.row(m.F(f, 0));
    const Eigen::Vector3d b = m.V.row(m.F(f, 1));
    const Eigen::Vector3d c = m.V.row(m.F(f, 2));
    EXPECT_GT((b - a).cross(c - a).z(), 0.0) << "face " << f << " points down";
  }
}

TEST(MeshImport, SaveRejectsInconsistentMeshes) {
  ScratchDir dir;
  const TriangleMesh cube = load_mesh(kCube);

  TriangleMesh bad_index = cube;
  bad_index.F(3, 1) = 8;
  EXPECT_NE(error_of([&] { save_mesh(bad_index, dir / "x.stl"); }).find("face 3"),
            std::string::npos);

  TriangleMesh bad_part = cube;
  bad_part.part(0) = 1;
  EXPECT_NE(error_of([&] { save_mesh(bad_part, dir / "x.obj"); }).find("part"), std::string::npos);

  TriangleMesh bad_position = cube;
  bad_position.V(2, 2) = std::numeric_limits<double>::quiet_NaN();
  error_of([&] { save_mesh(bad_position, dir / "x.stl"); });

  EXPECT_NE(error_of([&] { save_mesh(cube, dir / "x.vtk"); }).find(".vtk"), std::string::npos);
  EXPECT_NE(error_of([&] { save_mesh(TriangleMesh{}, dir / "x.stl"); }).find("no faces"),
            std::string::npos);
  EXPECT_FALSE(fs::exists(dir / "x.stl"));
}

TEST(MeshImport, SaveWithoutPartsWritesOnePart) {
  ScratchDir dir;
  TriangleMesh m = load_mesh(kCube);
  m.part.resize(0);
  m.part_names.clear();
  save_mesh(m, dir / "plain.obj");
  const TriangleMesh back = load_mesh(dir / "plain.obj");
  EXPECT_EQ(back.part_names, std::vector<std::string>{"mesh"});
  EXPECT_EQ(back.F.rows(), 12);
}

TEST(MeshImport, EmptyMeshHasEmptyBoxAndZeroArea) {
  const TriangleMesh empty;
  EXPECT_TRUE(mpmgeom::bounding_box(empty).isEmpty());
  EXPECT_EQ(mpmgeom::surface_area(empty), 0.0);
}

}  // namespace
