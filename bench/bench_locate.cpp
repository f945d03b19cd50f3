// Point location in a boundary-grid layer (DESIGN.md section 3, point 5): located points per
// second (items/s) for a cloud of particles flowing over a wavy terrain, with and without the
// per-A-cell skip flags (mpmgeom::layer_cell_flags, skip:1) and with the flags and the bounds of
// the layer in each flagged cell (mpmgeom::LayerCellFilter, skip:2), on one or two threads, with
// the particles in random order or sorted by A-cell as an MPM code keeps them.
//
// The layer is built by hand (wedges on a 100 x 100 vertex terrain sheet, ~20k triangles,
// extruded by t = h along area-weighted vertex normals), so the benchmark does not depend on
// extrude_layer.

#include <benchmark/benchmark.h>

#include <tbb/global_control.h>

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdint>
#include <memory>
#include <random>
#include <utility>
#include <vector>

#include "mpmgeom/coupling.hpp"
#include "mpmgeom/locator.hpp"

namespace {

constexpr int kSide = 100;        // terrain vertices per side
constexpr double kLength = 99.0;  // terrain extent per side, so triangles have legs h = 1
constexpr double kSpacing = 1.0;  // A-grid spacing h, also the layer thickness

double terrain(double x, double y) {
  return 5.0 * std::sin(x / 10.0) * std::cos(y / 13.0) + 2.0 * std::sin(x / 4.0 + y / 7.0);
}

mpmgeom::BoundaryGrid terrain_layer() {
  mpmgeom::BoundaryGrid g;
  g.dimension = 3;
  g.layers = 1;
  g.thickness = kSpacing;
  const int wall_nodes = kSide * kSide;
  const auto id = [](int i, int j) { return j * kSide + i; };
  Eigen::MatrixX3d wall(wall_nodes, 3);
  for (int j = 0; j < kSide; ++j) {
    for (int i = 0; i < kSide; ++i) {
      const double x = kLength * i / (kSide - 1), y = kLength * j / (kSide - 1);
      wall.row(id(i, j)) << x, y, terrain(x, y);
    }
  }
  std::vector<std::array<int, 3>> triangles;  // counter-clockwise seen from above (material)
  for (int j = 0; j + 1 < kSide; ++j) {
    for (int i = 0; i + 1 < kSide; ++i) {
      triangles.push_back({id(i, j), id(i + 1, j), id(i + 1, j + 1)});
      triangles.push_back({id(i, j), id(i + 1, j + 1), id(i, j + 1)});
    }
  }
  Eigen::MatrixX3d normal = Eigen::MatrixX3d::Zero(wall_nodes, 3);
  for (const auto& t : triangles) {
    const Eigen::Vector3d n = (wall.row(t[1]) - wall.row(t[0]))
                                  .transpose()
                                  .cross((wall.row(t[2]) - wall.row(t[0])).transpose());
    for (const int v : t) normal.row(v) += n.transpose();  // area weighted
  }
  normal.rowwise().normalize();
  g.nodes.resize(2 * wall_nodes, 3);
  g.nodes.topRows(wall_nodes) = wall;
  g.nodes.bottomRows(wall_nodes) = wall + kSpacing * normal;
  g.node_normals.resize(2 * wall_nodes, 3);
  g.node_normals << normal, normal;
  g.cells.resize(static_cast<Eigen::Index>(triangles.size()), 6);
  for (std::size_t c = 0; c < triangles.size(); ++c) {
    for (int k = 0; k < 3; ++k) {
      g.cells(static_cast<Eigen::Index>(c), k) = triangles[c][static_cast<std::size_t>(k)];
      g.cells(static_cast<Eigen::Index>(c), 3 + k) =
          wall_nodes + triangles[c][static_cast<std::size_t>(k)];
    }
  }
  g.cell_layer = Eigen::VectorXi::Zero(g.cells.rows());
  g.cell_part = Eigen::VectorXi::Zero(g.cells.rows());
  g.part_names = {"terrain"};
  return g;
}

/// Particles over the terrain: uniform in x, y and from 1 h below to 9 h above the ground
/// (a flow several cells deep; about a tenth of it lies in the layer).
Eigen::MatrixXd particle_cloud(int count) {
  std::mt19937_64 rng(42);
  std::uniform_real_distribution<double> u(0.0, 1.0);
  Eigen::MatrixXd points(count, 3);
  for (int n = 0; n < count; ++n) {
    const double x = kLength * u(rng), y = kLength * u(rng);
    points.row(n) << x, y, terrain(x, y) + kSpacing * (-1.0 + 10.0 * u(rng));
  }
  return points;
}

/// The A-grid covering the cloud and its per-cell flags from mpmgeom::layer_cell_flags: a
/// particle whose A-cell does not touch a layer cell's bounding box cannot be in the layer and
/// skips the query.
struct SkipGrid {
  mpmgeom::GridSpec spec;
  std::array<int, 3> cells{};
  std::vector<std::uint8_t> touches_layer;
  mpmgeom::LayerCellFilter filter;

  SkipGrid(const mpmgeom::BoundaryGrid& g, const Eigen::MatrixXd& points) {
    const Eigen::Vector3d lo =
        points.colwise().minCoeff().transpose().cwiseMin(g.nodes.colwise().minCoeff().transpose());
    const Eigen::Vector3d hi =
        points.colwise().maxCoeff().transpose().cwiseMax(g.nodes.colwise().maxCoeff().transpose());
    spec.dimension = 3;
    spec.spacing = kSpacing;
    spec.origin = lo - Eigen::Vector3d::Constant(kSpacing);
    for (int i = 0; i < 3; ++i) {
      cells[static_cast<std::size_t>(i)] =
          static_cast<int>(std::ceil((hi[i] - spec.origin[i]) / kSpacing)) + 1;
      spec.nodes[i] = cells[static_cast<std::size_t>(i)] + 1;
    }
    touches_layer = mpmgeom::layer_cell_flags(g, spec);
    filter = mpmgeom::LayerCellFilter(g, spec);
  }
  [[nodiscard]] int cell_of(double x, int axis) const {
    return static_cast<int>(std::floor((x - spec.origin[axis]) / kSpacing));
  }
  /// Linear A-cell index, last axis fastest (as layer_cell_flags numbers them).
  [[nodiscard]] std::size_t index(int a, int b, int d) const {
    return (static_cast<std::size_t>(a) * static_cast<std::size_t>(cells[1]) +
            static_cast<std::size_t>(b)) *
               static_cast<std::size_t>(cells[2]) +
           static_cast<std::size_t>(d);
  }
  /// skip[i] = 1 if point i's A-cell does not touch the layer, or (with `bounds`) the point
  /// lies outside the layer's bounds in it (recomputed every step in a simulation, so it is part
  /// of the timed loop).
  void flags(const Eigen::MatrixXd& points, std::vector<std::uint8_t>& skip, bool bounds) const {
    skip.resize(static_cast<std::size_t>(points.rows()));
    for (Eigen::Index n = 0; n < points.rows(); ++n) {
      const Eigen::Vector3i cell(cell_of(points(n, 0), 0), cell_of(points(n, 1), 1),
                                 cell_of(points(n, 2), 2));
      bool query = touches_layer[index(cell[0], cell[1], cell[2])] != 0;
      if (query && bounds) query = filter.may_hold(cell, points.row(n).transpose());
      skip[static_cast<std::size_t>(n)] = query ? 0 : 1;
    }
  }
};

struct Fixture {
  mpmgeom::BoundaryGrid layer = terrain_layer();
  mpmgeom::LayerLocator locator{layer};
};
const Fixture& fixture() {
  static const Fixture f;
  return f;
}

/// Particles in the order an MPM code keeps them: sorted by A-cell (last axis fastest).
Eigen::MatrixXd sorted_by_cell(const Eigen::MatrixXd& points, const SkipGrid& grid) {
  std::vector<std::pair<std::size_t, Eigen::Index>> keys(static_cast<std::size_t>(points.rows()));
  for (Eigen::Index n = 0; n < points.rows(); ++n) {
    keys[static_cast<std::size_t>(n)] = {
        grid.index(grid.cell_of(points(n, 0), 0), grid.cell_of(points(n, 1), 1),
                   grid.cell_of(points(n, 2), 2)),
        n};
  }
  std::sort(keys.begin(), keys.end());
  Eigen::MatrixXd sorted(points.rows(), 3);
  for (std::size_t k = 0; k < keys.size(); ++k) {
    sorted.row(static_cast<Eigen::Index>(k)) = points.row(keys[k].second);
  }
  return sorted;
}

// Args: points, skip (0 none, 1 flags, 2 flags and bounds), threads, particles sorted by A-cell
// (0/1).
void BM_LocateCloud(benchmark::State& state) {
  const auto count = static_cast<int>(state.range(0));
  const bool use_skip = state.range(1) != 0;
  const tbb::global_control threads(tbb::global_control::max_allowed_parallelism,
                                    static_cast<std::size_t>(state.range(2)));
  const Fixture& f = fixture();
  Eigen::MatrixXd points = particle_cloud(count);
  const SkipGrid skip_grid(f.layer, points);
  if (state.range(3) != 0) points = sorted_by_cell(points, skip_grid);
  std::vector<std::uint8_t> skip;
  std::vector<mpmgeom::LayerLocator::Location> out;
  for (auto _ : state) {
    if (use_skip) skip_grid.flags(points, skip, state.range(1) == 2);
    f.locator.locate(points, out, use_skip ? &skip : nullptr);
    benchmark::DoNotOptimize(out.data());
  }
  state.SetItemsProcessed(state.iterations() * count);
  const auto found =
      std::count_if(out.begin(), out.end(), [](const auto& l) { return l.cell >= 0; });
  state.counters["in_layer"] = static_cast<double>(found) / count;
  if (use_skip) {
    state.counters["skipped"] =
        static_cast<double>(std::count(skip.begin(), skip.end(), std::uint8_t{1})) / count;
  }
  state.counters["cells"] = static_cast<double>(f.layer.cell_count());
}
BENCHMARK(BM_LocateCloud)
    ->ArgNames({"points", "skip", "threads", "sorted"})
    ->Args({100000, 0, 1, 0})
    ->Args({1000000, 0, 1, 0})
    ->Args({1000000, 1, 1, 0})
    ->Args({1000000, 0, 1, 1})
    ->Args({1000000, 1, 1, 1})
    ->Args({1000000, 2, 1, 1})
    ->Args({1000000, 0, 2, 1})
    ->Args({1000000, 1, 2, 1})
    ->Args({1000000, 2, 2, 1})
    ->Unit(benchmark::kMillisecond)
    ->UseRealTime();

// Building the Embree BVH over the layer cells (once per static wall).
void BM_BuildLocator(benchmark::State& state) {
  const mpmgeom::BoundaryGrid& layer = fixture().layer;
  for (auto _ : state) {
    const mpmgeom::LayerLocator locator(layer);
    benchmark::DoNotOptimize(&locator);
  }
  state.SetItemsProcessed(state.iterations() * static_cast<int64_t>(layer.cell_count()));
}
BENCHMARK(BM_BuildLocator)->Unit(benchmark::kMillisecond)->UseRealTime();

}  // namespace

BENCHMARK_MAIN();
