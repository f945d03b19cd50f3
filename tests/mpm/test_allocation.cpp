// Issue 9: no allocation inside a step. Once a scene has settled (the first steps size its
// scratch buffers, grid blocks and coupling matrices), a step makes no heap allocation: counted
// here with every malloc of the process (support/allocation_counter.cpp replaces malloc in this
// test binary only), so Eigen temporaries, std::vector growth and TBB tasks all count.
// The dual-grid couplings (Blending mortar and one-way, Enhanced) may allocate in a step that
// factorises (Eigen's ordering and factorisation allocate; the active set of a flow changes
// most steps), and Blending in a step whose coupling joins other nodes (nodes crossing the
// coupling threshold: its matrices and blocks take a new shape, and until Blending solved such
// steps against the factorisation in hand they all factorised); a step that solves with the
// factorisations in hand and the same nodes allocates nothing.

#include <gtest/gtest.h>

#include <cstddef>
#include <string>

#include <nlohmann/json.hpp>

#include "mpm/solver.hpp"
#include "support/allocation_counter.hpp"
#include "support/scenes.hpp"
#include "support/shapes.hpp"

namespace {

using nlohmann::json;

struct Count {
  std::size_t steps = 0;        ///< steps counted
  std::size_t allocations = 0;  ///< over those steps
  std::size_t skipped = 0;      ///< steps that factorised or reshaped a coupling (not counted)
};

/// The couplings' factorisations and steps that joined other nodes so far: a step that adds to
/// either may allocate.
std::size_t coupling_changes(const mpm::Simulation& sim) {
  std::size_t total = 0;
  for (const auto& w : sim.coupling_work()) total += w.factorizations + w.reshaped_steps;
  return total;
}

/// Heap allocations over `steps` steps after `warmup` steps, leaving out the steps in which a
/// dual-grid coupling factorised or joined other nodes.
template <int D>
Count allocations_in_steps(const mpm::Scene& scene, int warmup = 20, int steps = 40) {
  mpm::Solver<D> solver(scene);
  const double dt = solver.stable_dt(0.3);
  for (int s = 0; s < warmup; ++s) solver.step(dt);
  Count count;
  for (int s = 0; s < steps; ++s) {
    const std::size_t changes = coupling_changes(solver);
    const std::size_t before = mpm::test::allocations();
    solver.step(dt);
    const std::size_t made = mpm::test::allocations() - before;
    EXPECT_FALSE(solver.fault().has_value()) << *solver.fault();
    if (coupling_changes(solver) != changes) {
      ++count.skipped;
      continue;
    }
    ++count.steps;
    count.allocations += made;
  }
  return count;
}

json moving_block(int dim, const std::string& update, const std::string& storage) {
  json doc = mpm::test::box_scene(dim, "bspline2", 0.1);
  doc["scheme"]["update"] = update;
  doc["grid"]["storage"] = storage;
  doc["bodies"][0]["velocity"] = dim == 1   ? json{0.5}
                                 : dim == 2 ? json{0.5, -0.3}
                                            : json{0.5, -0.3, 0.2};
  return doc;
}

/// A 3D block sliding along a floor under gravity: the box's zmin face, or a mesh plane 0.3 h
/// off the grid lines coupled by `method` (sdf, mortar, one-way).
json sliding_block(const std::string& method, const std::string& condition) {
  const double h = 0.1;
  json doc = mpm::test::box_scene(3, "bspline2", h);
  const double base = method == "face" ? 0.0 : 0.3 * h;
  doc["gravity"] = {0.0, 0.0, -9.81};
  doc["bodies"][0]["shape"]["min"] = {0.3, 0.3, base};
  doc["bodies"][0]["shape"]["max"] = {0.7, 0.7, base + 0.4};
  doc["bodies"][0]["velocity"] = {0.05, 0.02, 0.0};
  json wall = {{"condition", condition}, {"separable", true}};
  if (condition == "friction") wall["mu"] = 0.3;
  if (method == "face") {
    wall["face"] = "zmin";
  } else {
    wall["name"] = "floor";
    wall["surface"] = {
        {"type", "mesh"},
        {"file", mpm::test::floor_plane_file("mpm_test_allocation", base, -0.05, 1.05).string()},
        {"remesh", true}};
    wall["method"] = method;
  }
  doc["walls"] = json::array({wall});
  return doc;
}

TEST(Allocation, StandardStepsAllocateNothing) {
  for (const char* update : {"musl", "usl", "mls"}) {
    for (const char* storage : {"dense", "sparse"}) {
      const std::string what = std::string(update) + ", " + storage;
      const Count c1 = allocations_in_steps<1>(mpm::test::parse(moving_block(1, update, storage)));
      const Count c2 = allocations_in_steps<2>(mpm::test::parse(moving_block(2, update, storage)));
      const Count c3 = allocations_in_steps<3>(mpm::test::parse(moving_block(3, update, storage)));
      EXPECT_EQ(c1.allocations, 0U) << "1D " << what;
      EXPECT_EQ(c2.allocations, 0U) << "2D " << what;
      EXPECT_EQ(c3.allocations, 0U) << "3D " << what;
      EXPECT_EQ(c3.steps, 40U);
    }
  }
}

TEST(Allocation, GridFaceAndSdfWallsAllocateNothing) {
  for (const char* method : {"face", "sdf"}) {
    for (const char* condition : {"slip", "friction", "sticky"}) {
      const Count c = allocations_in_steps<3>(mpm::test::parse(sliding_block(method, condition)));
      EXPECT_EQ(c.allocations, 0U) << method << ", " << condition;
      EXPECT_EQ(c.steps, 40U);
    }
  }
}

// The dual-grid couplings: their per-step assembly and their solves by refinement against the
// factorisations in hand reuse the wall's buffers.
TEST(Allocation, DualGridCouplingsAllocateOnlyToFactorise) {
  for (const char* method : {"mortar", "one-way", "enhanced"}) {
    for (const char* condition : {"slip", "friction"}) {
      const Count c = allocations_in_steps<3>(mpm::test::parse(sliding_block(method, condition)));
      EXPECT_EQ(c.allocations, 0U) << method << ", " << condition;
      // Most steps solve with the factorisation in hand (a block sliding on a plane keeps its
      // active set); the test is empty otherwise.
      EXPECT_GE(c.steps, 30U) << method << ", " << condition << ": " << c.skipped
                              << " steps factorised or reshaped";
    }
  }
}

}  // namespace
