#pragma once
// Closed and open test surfaces built in code.

#include <algorithm>
#include <array>
#include <cmath>
#include <filesystem>
#include <map>
#include <string>
#include <utility>
#include <vector>

#include <unistd.h>

#include "mpmgeom/triangle_mesh.hpp"
#include "support/temp_directory.hpp"

namespace mpm::test {

/// Writes the floor plane z = level, two triangles over [lo, hi]^2 with normals up (one part,
/// "floor"), to an OBJ file in the temporary directory named after `name` and the level;
/// returns its path. Written under a name of this process's and then renamed into place, so
/// that another process writing the same file (two `mpm bench perf` tests run side by side
/// under `ctest -j2`) never lets a reader see it half written: each sees one whole copy.
/// A temporary directory that cannot be used (TMPDIR naming a file, or a path that does not
/// exist) throws std::runtime_error naming it.
inline std::filesystem::path floor_plane_file(const std::string& name, double level, double lo,
                                              double hi) {
  const std::filesystem::path directory = temporary_directory("the floor's mesh");
  const std::string stem = name + "_floor_" + std::to_string(level);
  const auto file = directory / (stem + ".obj");
  const auto partial = directory / (stem + "." + std::to_string(::getpid()) + ".obj");
  mpmgeom::TriangleMesh mesh;
  mesh.V.resize(4, 3);
  mesh.V << lo, lo, level, hi, lo, level, hi, hi, level, lo, hi, level;
  mesh.F.resize(2, 3);
  mesh.F << 0, 1, 2, 0, 2, 3;
  mesh.part = Eigen::VectorXi::Zero(2);
  mesh.part_names = {"floor"};
  mpmgeom::save_mesh(mesh, partial);
  std::filesystem::rename(partial, file);  // atomic within one file system
  return file;
}

/// Icosahedron refined `levels` times by splitting every triangle in four, vertices on the
/// sphere of radius `radius` about the origin; normals outward (or inward), one part "sphere".
inline mpmgeom::TriangleMesh icosphere(int levels, double radius = 1.0, bool outward = true) {
  const double t = (1.0 + std::sqrt(5.0)) / 2.0;
  std::vector<Eigen::Vector3d> v = {{-1, t, 0}, {1, t, 0}, {-1, -t, 0}, {1, -t, 0},
                                    {0, -1, t}, {0, 1, t}, {0, -1, -t}, {0, 1, -t},
                                    {t, 0, -1}, {t, 0, 1}, {-t, 0, -1}, {-t, 0, 1}};
  for (auto& p : v) p.normalize();
  std::vector<std::array<int, 3>> f = {{0, 11, 5}, {0, 5, 1},  {0, 1, 7},   {0, 7, 10}, {0, 10, 11},
                                       {1, 5, 9},  {5, 11, 4}, {11, 10, 2}, {10, 7, 6}, {7, 1, 8},
                                       {3, 9, 4},  {3, 4, 2},  {3, 2, 6},   {3, 6, 8},  {3, 8, 9},
                                       {4, 9, 5},  {2, 4, 11}, {6, 2, 10},  {8, 6, 7},  {9, 8, 1}};
  for (int level = 0; level < levels; ++level) {
    std::map<std::pair<int, int>, int> midpoint;
    auto mid = [&](int a, int b) {
      const auto key = std::minmax(a, b);
      const auto [it, inserted] = midpoint.try_emplace(key, static_cast<int>(v.size()));
      if (inserted) v.push_back((v[a] + v[b]).normalized());
      return it->second;
    };
    std::vector<std::array<int, 3>> finer;
    for (const auto& [a, b, c] : f) {
      const int ab = mid(a, b), bc = mid(b, c), ca = mid(c, a);
      finer.insert(finer.end(), {{a, ab, ca}, {b, bc, ab}, {c, ca, bc}, {ab, bc, ca}});
    }
    f = std::move(finer);
  }
  mpmgeom::TriangleMesh m;
  m.V.resize(static_cast<Eigen::Index>(v.size()), 3);
  for (std::size_t i = 0; i < v.size(); ++i) m.V.row(static_cast<Eigen::Index>(i)) = radius * v[i];
  m.F.resize(static_cast<Eigen::Index>(f.size()), 3);
  for (std::size_t i = 0; i < f.size(); ++i) {
    if (outward) {
      m.F.row(static_cast<Eigen::Index>(i)) << f[i][0], f[i][1], f[i][2];
    } else {
      m.F.row(static_cast<Eigen::Index>(i)) << f[i][0], f[i][2], f[i][1];
    }
  }
  m.part = Eigen::VectorXi::Zero(m.F.rows());
  m.part_names = {"sphere"};
  return m;
}

}  // namespace mpm::test
