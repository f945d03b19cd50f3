// Time of `mpm prep` (import, repair, remesh, extrude, couple, flag) on a synthetic terrain of
// about 10^6 triangles, written once to a binary STL in the temporary directory. One iteration per
// size: this is minutes of CGAL work, not a micro-benchmark.
//
//   build/bin/bench_prep                      # 10^6 triangles, h = 1 m (remeshed to ~h)
//   build/bin/bench_prep --benchmark_filter=/250   # the 1.25e5-triangle variant only

#include <benchmark/benchmark.h>

#include <cmath>
#include <filesystem>

#include "mpm/boundary_package.hpp"
#include "mpmgeom/triangle_mesh.hpp"

namespace {

/// n x n quads (2 n^2 triangles) over a 400 m x 400 m hillside with a channel and undulation.
std::filesystem::path terrain_file(int n) {
  const auto file =
      std::filesystem::temp_directory_path() / ("mpm_bench_terrain_" + std::to_string(n) + ".stl");
  if (std::filesystem::exists(file)) return file;
  mpmgeom::TriangleMesh mesh;
  mesh.V.resize(static_cast<Eigen::Index>(n + 1) * (n + 1), 3);
  for (int j = 0; j <= n; ++j) {
    for (int i = 0; i <= n; ++i) {
      const double x = 400.0 * i / n, y = 400.0 * j / n;
      const double z = 0.25 * (400.0 - x) - 6.0 * std::exp(-std::pow((y - 200.0) / 40.0, 2)) +
                       1.5 * std::sin(0.05 * x + 0.03 * y) * std::cos(0.04 * y);
      mesh.V.row(static_cast<Eigen::Index>(j) * (n + 1) + i) << x, y, z;
    }
  }
  mesh.F.resize(2L * n * n, 3);
  for (int j = 0; j < n; ++j) {
    for (int i = 0; i < n; ++i) {
      const int a = j * (n + 1) + i, b = a + 1, c = a + n + 1, d = c + 1;
      const Eigen::Index f = 2L * (static_cast<Eigen::Index>(j) * n + i);
      mesh.F.row(f) << a, b, d;
      mesh.F.row(f + 1) << a, d, c;
    }
  }
  mesh.part = Eigen::VectorXi::Zero(mesh.F.rows());
  mesh.part_names = {"terrain"};
  mpmgeom::save_mesh(mesh, file);
  return file;
}

void BM_PrepTerrain(benchmark::State& state) {
  const int n = static_cast<int>(state.range(0));
  const auto file = terrain_file(n);
  const double h = 1.0;
  mpm::PrepOptions options;
  options.layer.thickness = h;
  Eigen::VectorXd lo(3), hi(3);
  lo << -4.0, -4.0, -20.0;
  hi << 404.0, 404.0, 112.0;
  const mpmgeom::GridSpec grid = mpm::standard_grid_spec(3, lo, hi, h, mpm::ShapeKind::bspline2);
  std::size_t cells = 0;
  for (auto _ : state) {
    const mpm::BoundaryPackage p = mpm::prepare_boundary(file, options, grid);
    cells = p.report.cells;
  }
  state.counters["input_triangles"] = 2.0 * n * n;
  state.counters["layer_cells"] = static_cast<double>(cells);
}
BENCHMARK(BM_PrepTerrain)->Arg(250)->Arg(708)->Unit(benchmark::kSecond)->Iterations(1);

}  // namespace

BENCHMARK_MAIN();
