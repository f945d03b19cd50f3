// The standard grid's two storage layouts (grid.hpp): dense over the box, and sparse by blocks
// with memory only where particles have been. Both number every node once, the step gives
// bit-identical results in either (the same sums in the same order), a sparse block keeps its
// five arrays in one run of memory, and a sparse grid holds memory in proportion to the blocks a
// body covers, not to its box, and hands it back behind a moving body.

#include <gtest/gtest.h>

#include <algorithm>
#include <cstdint>
#include <cstdio>
#include <fstream>
#include <numeric>
#include <set>
#include <string>
#include <utility>
#include <vector>

#include "mpm/solver.hpp"
#include "support/scenes.hpp"

namespace mpm {
namespace {

/// Where every node's five values lie: inside the grid's storage, no two overlapping; in the
/// sparse layout inside the node's block's run of kBlockBytes (a block's arrays together); at
/// the place the compile-time layout (Grid::access) and the per-axis byte offsets
/// (Grid::byte_offset, summed over the axes) say.
template <int D>
void check_memory(Grid<D>& g) {
  const char* begin = static_cast<const char*>(g.storage.data());
  const char* end = begin + g.storage.bytes();
  std::vector<std::pair<const char*, std::size_t>> spans;  // (first byte, size)
  auto check = [&](auto& array, const Index<D>& i, int n) {
    using T = typename std::decay_t<decltype(array)>::value_type;
    const auto node = static_cast<std::size_t>(n);
    const char* at = reinterpret_cast<const char*>(&array[node]);
    EXPECT_GE(at, begin);
    EXPECT_LE(at + sizeof(T), end);
    spans.emplace_back(at, sizeof(T));
    const auto* fixed = reinterpret_cast<const char*>(
        g.sparse ? &g.template access<true>(array)[node] : &g.template access<false>(array)[node]);
    EXPECT_EQ(fixed, at) << "node " << n;
    std::ptrdiff_t sum = 0;
    for (int d = 0; d < D; ++d) sum += g.template byte_offset<sizeof(T)>(g.axis_offset(d, i[d]));
    EXPECT_EQ(array.base() + sum, at) << "node " << n;
    if (g.sparse) {
      const std::size_t block = node / Grid<D>::kBlockNodes;
      EXPECT_GE(at, begin + block * Grid<D>::kBlockBytes) << "node " << n;
      EXPECT_LE(at + sizeof(T), begin + (block + 1) * Grid<D>::kBlockBytes) << "node " << n;
    }
  };
  Index<D> i = Index<D>::Zero();
  const long count = g.nodes.template cast<long>().prod();
  for (long k = 0; k < count; ++k) {
    const int n = g.linear(i);
    check(g.mass, i, n);
    check(g.momentum, i, n);
    check(g.force, i, n);
    check(g.velocity, i, n);
    check(g.velocity_new, i, n);
    for (int d = D - 1; d >= 0 && ++i[d] == g.nodes[d]; --d) i[d] = 0;
  }
  std::sort(spans.begin(), spans.end());
  for (std::size_t k = 1; k < spans.size(); ++k) {
    EXPECT_LE(spans[k - 1].first + spans[k - 1].second, spans[k].first) << "values overlap";
  }
}

template <int D>
void check_numbering(bool sparse) {
  Grid<D> g;
  Index<D> nodes;
  for (int d = 0; d < D; ++d) nodes[d] = 7 + 2 * d;  // not multiples of the block
  g.resize(Vec<D>::Zero(), 0.5, nodes, sparse);
  std::set<int> seen;
  Index<D> i = Index<D>::Zero();
  const long count = nodes.template cast<long>().prod();
  for (long k = 0; k < count; ++k) {
    const int n = g.linear(i);
    ASSERT_GE(n, 0);
    ASSERT_LT(static_cast<std::size_t>(n), g.size());
    EXPECT_TRUE(seen.insert(n).second) << "node " << n << " numbered twice";
    EXPECT_EQ(g.multi(n), i);
    int sum = 0;
    for (int d = 0; d < D; ++d) sum += g.axis_offset(d, i[d]);
    EXPECT_EQ(sum, n);  // separable: the stencils rely on it
    const int block = g.block_of(n);
    EXPECT_EQ(block, g.block_index((i.array() / Grid<D>::kBlock).matrix()));
    bool found = false;
    g.for_each_node(block, [&](std::size_t m) { found |= m == static_cast<std::size_t>(n); });
    EXPECT_TRUE(found) << "node " << n << " not visited with its block";
    for (int d = D - 1; d >= 0 && ++i[d] == nodes[d]; --d) i[d] = 0;
  }
  EXPECT_EQ(static_cast<long>(seen.size()), count);
  check_memory(g);
}

TEST(GridStorage, BothLayoutsNumberEveryNodeOnce) {
  for (const bool sparse : {false, true}) {
    check_numbering<1>(sparse);
    check_numbering<2>(sparse);
    check_numbering<3>(sparse);
  }
}

nlohmann::json falling_block(int dim, const std::string& shape, const std::string& storage) {
  nlohmann::json doc = test::box_scene(dim, shape);
  doc["grid"]["storage"] = storage;
  nlohmann::json g = nlohmann::json::array();
  for (int d = 0; d < dim; ++d) g.push_back(d + 1 == dim ? -9.81 : 0.0);
  doc["gravity"] = g;
  doc["bodies"][0]["velocity"] = g;  // moving from the start
  doc["walls"] = {{{"face", dim == 1   ? "xmin"
                            : dim == 2 ? "ymin"
                                       : "zmin"},
                   {"condition", "friction"},
                   {"mu", 0.3}}};
  return doc;
}

template <int D>
void check_identical(const std::string& shape) {
  Solver<D> dense(test::parse(falling_block(D, shape, "dense")));
  Solver<D> sparse(test::parse(falling_block(D, shape, "sparse")));
  ASSERT_FALSE(dense.grid.sparse);
  ASSERT_TRUE(sparse.grid.sparse);
  const double dt = dense.stable_dt(0.4);
  for (int step = 0; step < 60; ++step) {
    dense.step(dt);
    sparse.step(dt);
  }
  ASSERT_EQ(dense.particles.size(), sparse.particles.size());
  // The same sums in the same order, but not the same machine code: every dimension's transfers
  // are compiled once per layout (the layout is a template parameter: Grid::access,
  // sample_grid_nodes()), and the compiler may contract multiply-adds into fused ones
  // differently in the two copies (it did in 2D with -march=native on an AVX-512 machine:
  // positions 2.8e-17 m apart after 60 steps, where another machine gave equal bits). Equal to
  // round-off, then: 60 steps of relative 1e-16 differences, amplified at most by the step's
  // stiffness. A wrong or missed node differs by the order of the weights, not of round-off.
  const double tol = 1e-12;
  double worst = 0.0;
  for (std::size_t p = 0; p < dense.particles.size(); ++p) {
    const double x = (dense.particles.position[p] - sparse.particles.position[p]).norm();
    const double v = (dense.particles.velocity[p] - sparse.particles.velocity[p]).norm();
    const double s = (dense.particles.stress[p] - sparse.particles.stress[p]).norm();
    worst = std::max({worst, x, v / 10.0, s / dense.particles.stress[p].norm()});
    ASSERT_LE(x, tol) << shape << " particle " << p;
    ASSERT_LE(v, 10.0 * tol) << shape << " particle " << p;  // speeds up to ~ 3 m/s
    ASSERT_LE(s, tol * dense.particles.stress[p].norm()) << shape << " particle " << p;
  }
  EXPECT_LE((dense.wall_impulses()[0] - sparse.wall_impulses()[0]).norm(),
            tol * dense.wall_impulses()[0].norm());
  std::printf("D = %d %s: largest difference %.2e\n", D, shape.c_str(), worst);
}

TEST(GridStorage, DenseAndSparseLayoutsGiveTheSameStep) {
  for (const char* shape : {"linear", "gimp", "bspline2"}) {
    check_identical<1>(shape);
    check_identical<2>(shape);
    check_identical<3>(shape);
  }
}

// After a step, every node its gathers marked (Grid::stencil_mark) says truly whether the
// 3^3 stencil starting at it has every node above the mass threshold: a wrong "yes" would sum
// over an empty node, a wrong "no" only cost time. A falling block on a friction floor, with a
// mass threshold of a fifth of a particle's mass, so that the nodes at the edge of the surface
// particles' stencils fall below it (at the default, 1e-9, a particle's own weights put every
// node of its stencil above): inside stencils full, surface ones not, in both layouts, over
// several steps (the epoch moves on with the masses and earlier marks must not count), and
// across the epoch's wrap (127 steps).
TEST(GridStorage, StencilMarksAgreeWithTheMasses) {
  for (const char* storage : {"dense", "sparse"}) {
    nlohmann::json doc = falling_block(3, "bspline2", storage);
    doc["scheme"]["mass_threshold"] = 0.2;
    const Scene scene = test::parse(doc);
    Solver<3> s(scene);
    const double mean = std::accumulate(s.particles.mass.begin(), s.particles.mass.end(), 0.0) /
                        static_cast<double>(s.particles.size());
    const double threshold = scene.mass_threshold * mean;
    const double dt = s.stable_dt(0.4);
    const Grid<3>& g = s.grid;
    for (int step = 0; step < 140; ++step) {
      s.step(dt);
      if (step % 20 != 0 && step < 125) continue;
      const auto epoch = static_cast<std::int8_t>(g.stencil_epoch);
      std::size_t full = 0, partial = 0;
      for (int i = 0; i + 2 < g.nodes[0]; ++i) {
        for (int j = 0; j + 2 < g.nodes[1]; ++j) {
          for (int k = 0; k + 2 < g.nodes[2]; ++k) {
            const int first = g.linear(Index<3>(i, j, k));
            const std::int8_t mark = g.stencil_mark[static_cast<std::size_t>(first)];
            if (mark != epoch && mark != -epoch) continue;
            bool all = true;
            for (int a = 0; a < 3; ++a) {
              for (int b = 0; b < 3; ++b) {
                for (int c = 0; c < 3; ++c) {
                  all &= g.mass[static_cast<std::size_t>(g.linear(Index<3>(i + a, j + b, k + c)))] >
                         threshold;
                }
              }
            }
            ASSERT_EQ(mark == epoch, all)
                << storage << " step " << step << " node " << i << "," << j << "," << k;
            ++(all ? full : partial);
          }
        }
      }
      EXPECT_GT(full, 0U) << storage << " step " << step;
      EXPECT_GT(partial, 0U) << storage << " step " << step;
    }
    EXPECT_EQ(g.stencil_epoch, 140 - 127);  // one epoch per step's masses, wrapped once
  }
}

/// Resident set of this process (kB), from /proc/self/status.
long resident_kb() {
  std::ifstream status("/proc/self/status");
  std::string key;
  while (status >> key) {
    if (key == "VmRSS:") {
      long kb = 0;
      status >> kb;
      return kb;
    }
    status.ignore(1 << 12, '\n');
  }
  return -1;
}

TEST(GridStorage, SparseGridHoldsMemoryWhereTheBodyIsAndReturnsIt) {
  // A 0.4 m block crossing a 6 x 2 x 2 m box at 20 m/s (h = 0.05 m: 125 x 45 x 45 nodes, 26 MB
  // stored densely); the block covers 2% of the box's blocks.
  nlohmann::json doc = test::box_scene(3, "bspline2", 0.05);
  doc["grid"]["max"] = {6.0, 2.0, 2.0};
  doc["bodies"][0]["shape"]["min"] = {0.3, 0.8, 0.8};
  doc["bodies"][0]["shape"]["max"] = {0.7, 1.2, 1.2};
  doc["bodies"][0]["velocity"] = {20.0, 0.0, 0.0};
  const long before = resident_kb();
  Solver<3> s(test::parse(doc));
  ASSERT_TRUE(s.grid.sparse) << "auto storage should choose sparse for a body in 2% of the box";
  const double box = static_cast<double>(s.grid.box_bytes());
  const double dt = s.stable_dt(0.4);
  double most = 0.0;
  for (int step = 0; step < 700; ++step) {  // over 4 m: 20 blocks' width
    s.step(dt);
    most = std::max(most, static_cast<double>(s.grid.committed_bytes()));
  }
  EXPECT_GT(s.particles.position[0].x(), 4.0);
  // A block's five arrays are stored together (6.5 kB): it overlaps at most 3 pages of 4 kB
  // (12 kB, 1.85 times its need), and the blocks the body left up to 48 steps ago (idle for
  // kReleaseAfter = 32 steps, released every 16) may still be held: 0.27 m at this speed, 1.4
  // blocks behind a body whose active blocks are 4 wide. So at most 1.85 x 5.4 / 4 = 2.5 times
  // what the active blocks need; the bound is 3 (measured 1.9; 2.9 with the arrays apart).
  const double active = static_cast<double>(s.grid.peak_active);
  EXPECT_LT(most, 3.0 * active) << "most " << most << " active " << active;
  EXPECT_LT(most, 0.1 * box);
  // What the process really holds agrees: far below the dense box.
  const long after = resident_kb();
  ASSERT_GT(before, 0);
  EXPECT_LT(static_cast<double>(after - before) * 1024.0, 0.3 * box)
      << "resident grew by " << after - before << " kB, the box is " << box / 1024 << " kB";
  std::printf("box %.1f MB, most held %.2f MB, active blocks at most %.2f MB, resident +%ld kB\n",
              box / 1e6, most / 1e6, active / 1e6, after - before);
}

}  // namespace
}  // namespace mpm
