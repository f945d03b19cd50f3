#pragma once
// Stepping a simulation in tests.

#include <gtest/gtest.h>

#include <algorithm>
#include <functional>

#include "mpm/solver.hpp"

namespace mpm::test {

/// Steps to `end` with the scene's CFL number, calling `observe(t, dt)` after every step; a
/// numerical fault fails the calling test.
inline void run_until(Simulation& sim, const Scene& scene, double end,
                      const std::function<void(double, double)>& observe) {
  double t = 0.0;
  while (t < end - 1e-12 * end) {
    const double dt = std::min(sim.stable_dt(scene.cfl), end - t);
    sim.step(dt);
    t += dt;
    ASSERT_FALSE(sim.fault().has_value()) << "t = " << t << ": " << *sim.fault();
    observe(t, dt);
  }
}

}  // namespace mpm::test
