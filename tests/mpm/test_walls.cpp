// Wall conditions on a node's velocity (walls.hpp) against exact answers: at a concave corner or
// crease the node may enter none of its facets, and the velocity is the nearest one that does
// not (Euclidean projection onto the cone of the facets' normals), with Coulomb friction taking
// at most mu times that projection's impulse from the sliding speed. And Enhanced's contact
// active set (update_contact()), one multiplier's pass at a time.

#include <gtest/gtest.h>

#include <array>
#include <cmath>
#include <numbers>
#include <random>
#include <vector>

#include "mpm/dual_grid.hpp"
#include "mpm/walls.hpp"

namespace mpm {
namespace {

constexpr double kTol = 1e-14;

template <int D>
Vec<D> corner(const std::vector<Vec<D>>& n, const Vec<D>& v, bool separable = true,
              const WallCondition& condition = Slip{}) {
  return std::visit(
      [&](const auto& c) {
        return constrain_velocity_in_corner<D>(c, separable, n.data(), static_cast<int>(n.size()),
                                               v);
      },
      condition);
}

// The foot of a wall on a floor (2D): floor normal +y, wall normal -x (material on the left of
// the floor and in front of the wall).
const std::vector<Vec<2>> kFoot = {Vec<2>(0.0, 1.0), Vec<2>(-1.0, 0.0)};

TEST(CornerCondition, FlowIntoTheFootOfAWallStops) {
  // Along the floor into the wall: the floor allows it, the wall does not; the nearest velocity
  // entering neither is rest (the node's own normal, the bisector, would keep (1, 1) / 2 * 2,
  // into the wall: the leak this condition closes).
  EXPECT_LT((corner<2>(kFoot, Vec<2>(2.0, 0.0)) - Vec<2>::Zero()).norm(), kTol);
  // Rising: the wall takes the normal part only.
  EXPECT_LT((corner<2>(kFoot, Vec<2>(2.0, 1.0)) - Vec<2>(0.0, 1.0)).norm(), kTol);
  // Into both: rest.
  EXPECT_LT(corner<2>(kFoot, Vec<2>(2.0, -1.0)).norm(), kTol);
  // Down along the wall into the floor: the floor takes it.
  EXPECT_LT((corner<2>(kFoot, Vec<2>(-0.5, -3.0)) - Vec<2>(-0.5, 0.0)).norm(), kTol);
}

TEST(CornerCondition, SeparableLeavesMotionAwayFromBothFacetsAlone) {
  const Vec<2> away(-1.0, 2.0);
  EXPECT_EQ(corner<2>(kFoot, away), away);
  EXPECT_EQ(corner<2>(kFoot, away, true, Sticky{}), away);
  EXPECT_EQ(corner<2>(kFoot, away, true, Friction{0.5}), away);
  // Bonded: the node slides along neither facet of a 2D corner.
  EXPECT_LT(corner<2>(kFoot, away, false).norm(), kTol);
}

TEST(CornerCondition, ObtuseCornerProjectsOntoTheFacetItEnters) {
  // Floor +y and a 45 degree ramp rising from it (normal (-1, 1) / sqrt 2): sliding along the
  // floor at 1 enters only the ramp, and leaves along the ramp at (1/2, 1/2).
  const std::vector<Vec<2>> ramp = {Vec<2>(0.0, 1.0), Vec<2>(-1.0, 1.0) / std::numbers::sqrt2};
  EXPECT_LT((corner<2>(ramp, Vec<2>(1.0, 0.0)) - Vec<2>(0.5, 0.5)).norm(), kTol);
  // Coulomb: the impulse removed is |(1/2, -1/2)| = 1/sqrt 2; mu = 0.5 takes 0.5 / sqrt 2 of the
  // remaining speed 1 / sqrt 2, half of it.
  EXPECT_LT((corner<2>(ramp, Vec<2>(1.0, 0.0), true, Friction{0.5}) - Vec<2>(0.25, 0.25)).norm(),
            kTol);
}

TEST(CornerCondition, FrictionTakesAtMostMuTimesTheNormalImpulse) {
  // (2, 3) into the foot: the wall removes 2 (normal), leaving (0, 3) sliding up the wall;
  // mu = 0.5 takes 1 of it. mu = 2 would take 4: the node stops.
  EXPECT_LT((corner<2>(kFoot, Vec<2>(2.0, 3.0), true, Friction{0.5}) - Vec<2>(0.0, 2.0)).norm(),
            kTol);
  EXPECT_LT(corner<2>(kFoot, Vec<2>(2.0, 3.0), true, Friction{2.0}).norm(), kTol);
  EXPECT_LT(corner<2>(kFoot, Vec<2>(2.0, 3.0), true, Sticky{}).norm(), kTol);
}

TEST(CornerCondition, ReportsEachFacetsNormalPush) {
  // Into both facets of the foot at (2, -1): the floor pushes up by 1, the wall back by 2. With
  // friction the change less those pushes is the friction's (here none: the node stops).
  std::array<double, 2> l{};
  const Vec<2> u = constrain_velocity_in_corner<2>(Friction{0.4}, true, kFoot.data(), 2,
                                                   Vec<2>(2.0, -1.0), l.data());
  EXPECT_LT(u.norm(), kTol);
  EXPECT_NEAR(l[0], 1.0, kTol);
  EXPECT_NEAR(l[1], 2.0, kTol);
  // Rising into the wall: the wall alone pushes; friction takes 0.4 * 2 of the sliding 3.
  const Vec<2> r = constrain_velocity_in_corner<2>(Friction{0.4}, true, kFoot.data(), 2,
                                                   Vec<2>(2.0, 3.0), l.data());
  EXPECT_NEAR(l[0], 0.0, kTol);
  EXPECT_NEAR(l[1], 2.0, kTol);
  EXPECT_LT((r - Vec<2>(0.0, 2.2)).norm(), kTol);
  // Bonded: the pushes that hold the node, whatever their sign.
  constrain_velocity_in_corner<2>(Slip{}, false, kFoot.data(), 2, Vec<2>(-1.0, 2.0), l.data());
  EXPECT_NEAR(l[0], -2.0, kTol);
  EXPECT_NEAR(l[1], -1.0, kTol);
}

TEST(CornerCondition, CreaseIn3DSlidesAlongItsLine) {
  // Terrain +z meeting a barrier with normal -x: the crease runs along y.
  const std::vector<Vec<3>> crease = {Vec<3>(0.0, 0.0, 1.0), Vec<3>(-1.0, 0.0, 0.0)};
  EXPECT_LT((corner<3>(crease, Vec<3>(2.0, 1.5, -1.0)) - Vec<3>(0.0, 1.5, 0.0)).norm(), kTol);
  EXPECT_LT((corner<3>(crease, Vec<3>(2.0, 1.5, 1.0)) - Vec<3>(0.0, 1.5, 1.0)).norm(), kTol);
  EXPECT_LT((corner<3>(crease, Vec<3>(2.0, 1.5, 1.0), false) - Vec<3>(0.0, 1.5, 0.0)).norm(), kTol);
  // A box corner: three facets, the node held.
  const std::vector<Vec<3>> box = {Vec<3>(1.0, 0.0, 0.0), Vec<3>(0.0, 1.0, 0.0),
                                   Vec<3>(0.0, 0.0, 1.0)};
  EXPECT_LT((corner<3>(box, Vec<3>(-1.0, -2.0, 3.0)) - Vec<3>(0.0, 0.0, 3.0)).norm(), kTol);
  EXPECT_LT(corner<3>(box, Vec<3>(-1.0, -2.0, -3.0)).norm(), kTol);
}

/// constrain_velocity_in_corner_of_parts() with one condition per facet.
template <int D>
Vec<D> parts_corner(const std::vector<Vec<D>>& n, const std::vector<WallCondition>& conditions,
                    const Vec<D>& v, bool separable = true) {
  std::vector<const WallCondition*> c;
  for (const auto& condition : conditions) c.push_back(&condition);
  std::vector<double> lambda(n.size());
  return constrain_velocity_in_corner_of_parts<D>(c.data(), separable, n.data(),
                                                  static_cast<int>(n.size()), v, lambda.data());
}

// A barrier's foot on terrain with other friction (the debris scene: terrain mu 0.25, barrier
// 0.36): each facet's friction counts in proportion to its push; until 2026-12-06 the node took
// the condition of one facet's part (the last in the mesh's order), whichever it pressed on.
TEST(CornerCondition, EachFacetsPartGivesItsOwnFriction) {
  const std::vector<WallCondition> floor_and_wall = {Friction{0.2}, Friction{0.6}};
  // Rising into the wall (2, 3): only the wall pushes (by 2), so the wall's mu = 0.6 takes 1.2
  // of the sliding 3.
  EXPECT_LT((parts_corner<2>(kFoot, floor_and_wall, Vec<2>(2.0, 3.0)) - Vec<2>(0.0, 1.8)).norm(),
            kTol);
  // Sliding back along the floor and into it (-2, -3): only the floor pushes (by 3), its mu =
  // 0.2 takes 0.6 of the sliding 2.
  EXPECT_LT((parts_corner<2>(kFoot, floor_and_wall, Vec<2>(-2.0, -3.0)) - Vec<2>(-1.4, 0.0)).norm(),
            kTol);
  // Along a crease in 3D, pressing on both: the terrain pushes by 0.1, the barrier by 0.2, so
  // mu = (0.2 * 0.1 + 0.6 * 0.2) / 0.3 of the normal change |(0.2, 0, -0.1)| = sqrt(0.05) is
  // taken from the speed 3 along the crease.
  const std::vector<Vec<3>> crease = {Vec<3>(0.0, 0.0, 1.0), Vec<3>(-1.0, 0.0, 0.0)};
  const std::vector<WallCondition> terrain_and_barrier = {Friction{0.2}, Friction{0.6}};
  const double taken = (0.2 * 0.1 + 0.6 * 0.2) / 0.3 * std::sqrt(0.05);
  EXPECT_LT((parts_corner<3>(crease, terrain_and_barrier, Vec<3>(0.2, 3.0, -0.1)) -
             Vec<3>(0.0, 3.0 - taken, 0.0))
                .norm(),
            kTol);
  // A slip facet adds no friction: pressing on both with the terrain frictionless, the
  // barrier's 0.6 counts for its share of the pushes only.
  const std::vector<WallCondition> slip_terrain = {Slip{}, Friction{0.6}};
  const double barrier_only = 0.6 * 0.2 / 0.3 * std::sqrt(0.05);
  EXPECT_LT((parts_corner<3>(crease, slip_terrain, Vec<3>(0.2, 3.0, -0.1)) -
             Vec<3>(0.0, 3.0 - barrier_only, 0.0))
                .norm(),
            kTol);
  // Both frictionless: slip along the crease.
  EXPECT_LT(
      (parts_corner<3>(crease, {Slip{}, Slip{}}, Vec<3>(0.2, 3.0, -0.1)) - Vec<3>(0.0, 3.0, 0.0))
          .norm(),
      kTol);
  // A sticky barrier holds a node pressing on it, not one that only rests on the terrain.
  const std::vector<WallCondition> sticky_wall = {Friction{0.2}, Sticky{}};
  EXPECT_LT(parts_corner<2>(kFoot, sticky_wall, Vec<2>(2.0, 3.0)).norm(), kTol);
  EXPECT_LT((parts_corner<2>(kFoot, sticky_wall, Vec<2>(-2.0, -3.0)) - Vec<2>(-1.4, 0.0)).norm(),
            kTol);
  // Moving away from both (separable): untouched whatever the conditions.
  EXPECT_EQ(parts_corner<2>(kFoot, sticky_wall, Vec<2>(-1.0, 2.0)), Vec<2>(-1.0, 2.0));
}

// With one condition on every facet the facets' parts make no difference: the same velocity as
// constrain_velocity_in_corner() with that condition, separable or bonded (random 3D corners of
// three facets).
TEST(CornerCondition, OneConditionOnEveryFacetIsTheCornerCondition) {
  std::mt19937 rng(11);
  std::uniform_real_distribution<double> u(-1.0, 1.0);
  for (int trial = 0; trial < 200; ++trial) {
    std::vector<Vec<3>> n;
    for (int i = 0; i < 3; ++i) n.push_back(Vec<3>(0.8 * u(rng), 0.8 * u(rng), 1.0).normalized());
    const Vec<3> v(u(rng), u(rng), u(rng));
    for (const WallCondition& c :
         {WallCondition(Slip{}), WallCondition(Sticky{}), WallCondition(Friction{0.3})}) {
      for (const bool separable : {true, false}) {
        const Vec<3> expected = corner<3>(n, v, separable, c);
        const Vec<3> got = parts_corner<3>(n, {c, c, c}, v, separable);
        EXPECT_LT((got - expected).norm(), 1e-12 * (1.0 + v.norm()));
      }
    }
  }
}

// Against the definition: the result enters no facet, and no velocity that enters none is closer
// to v (checked on a fine sample of the cone's boundary and interior); with one normal it is
// constrain_velocity().
TEST(CornerCondition, IsTheNearestVelocityEnteringNoFacet) {
  std::mt19937 rng(7);
  std::uniform_real_distribution<double> u(-1.0, 1.0);
  for (int trial = 0; trial < 200; ++trial) {
    // Three facet normals within 60 degrees of +z (a concave corner's cone has an interior).
    std::vector<Vec<3>> n;
    for (int i = 0; i < 3; ++i) {
      n.push_back(Vec<3>(0.8 * u(rng), 0.8 * u(rng), 1.0).normalized());
    }
    const Vec<3> v(u(rng), u(rng), u(rng));
    const Vec<3> p = corner<3>(n, v);
    for (const auto& ni : n) EXPECT_GE(ni.dot(p), -1e-12);
    double best = std::numeric_limits<double>::infinity();
    for (int s = 0; s < 20000; ++s) {
      const Vec<3> q = 2.0 * Vec<3>(u(rng), u(rng), u(rng));
      bool inside = true;
      for (const auto& ni : n) inside = inside && ni.dot(q) >= 0.0;
      if (inside) best = std::min(best, (q - v).norm());
    }
    EXPECT_LE((p - v).norm(), best + 1e-12);
  }
  for (int trial = 0; trial < 100; ++trial) {
    const std::vector<Vec<2>> one = {Vec<2>(u(rng), u(rng)).normalized()};
    const Vec<2> v(u(rng), u(rng));
    for (const WallCondition& c : {WallCondition(Slip{}), WallCondition(Friction{0.3})}) {
      for (const bool separable : {true, false}) {
        const Vec<2> a = corner<2>(one, v, separable, c);
        const Vec<2> b = std::visit(
            [&](const auto& cond) { return constrain_velocity<2>(cond, separable, one[0], v); }, c);
        EXPECT_LT((a - b).norm(), 1e-14);
      }
    }
  }
}

// Enhanced's active-set loop, one multiplier at a time (update_contact(), mpm/dual_grid.hpp):
// a floor with normal +y, the multiplier's impulse `total` and the coupled field's velocity
// `gap` at it, as one pass of the loop leaves them.
const Vec<2> kUp(0.0, 1.0);

struct Multiplier {
  Contact state = Contact::stick;
  unsigned char releases = 0;
  Vec<2> load = Vec<2>::Zero();
  bool kept_released = false;
  /// One pass with this impulse and gap; whether the loop must solve again.
  bool pass(const Vec<2>& total, const Vec<2>& gap, double mu = 0.4, bool separable = true,
            Contact on = Contact::stick) {
    return update_contact<2>(state, releases, load, on, mu, separable, kUp, total, gap,
                             kept_released);
  }
};

TEST(ContactActiveSet, AMultiplierReleasedTwiceInAStepStaysReleased) {
  // Rough contact: held, the multiplier pulls; released, the field closes its gap. Without a
  // limit the loop would alternate until its passes ran out, factorising every time.
  Multiplier m;
  const Vec<2> pulling(0.0, -1.0), closing(0.0, -0.5);
  EXPECT_TRUE(m.pass(pulling, Vec<2>::Zero()));  // released (1)
  EXPECT_EQ(m.state, Contact::off);
  EXPECT_TRUE(m.pass(Vec<2>::Zero(), closing));  // held again
  EXPECT_EQ(m.state, Contact::stick);
  EXPECT_TRUE(m.pass(pulling, Vec<2>::Zero()));  // released (2)
  EXPECT_EQ(m.releases, 2);
  // Its gap closes again: it stays released, the loop is told nothing changed (and settles).
  EXPECT_FALSE(m.pass(Vec<2>::Zero(), closing));
  EXPECT_EQ(m.state, Contact::off);
  EXPECT_TRUE(m.kept_released);
  // An opening gap leaves a released multiplier alone, and is not a kept release.
  EXPECT_FALSE(m.pass(Vec<2>::Zero(), Vec<2>(0.0, 0.5)));
  EXPECT_FALSE(m.kept_released);
  // A fresh step (releases reset by the caller) takes it back.
  m.releases = 0;
  EXPECT_TRUE(m.pass(Vec<2>::Zero(), closing));
  EXPECT_EQ(m.state, Contact::stick);
}

TEST(ContactActiveSet, ABondedWallHoldsAPullingMultiplier) {
  Multiplier m;
  EXPECT_FALSE(m.pass(Vec<2>(0.0, -1.0), Vec<2>::Zero(), 0.4, false));
  EXPECT_EQ(m.state, Contact::stick);
  EXPECT_EQ(m.releases, 0);
}

TEST(ContactActiveSet, StickSlipsBeyondMuTimesTheNormalImpulse) {
  // Pushed by 2 along +y: mu = 0.4 holds a tangential impulse up to 0.8.
  Multiplier m;
  EXPECT_FALSE(m.pass(Vec<2>(0.8, 2.0), Vec<2>::Zero()));  // on the cone: sticks
  EXPECT_EQ(m.state, Contact::stick);
  EXPECT_FALSE(m.pass(Vec<2>(0.8 * (1.0 + 5e-10), 2.0), Vec<2>::Zero()));  // within 1e-9
  EXPECT_TRUE(m.pass(Vec<2>(-1.5, 2.0), Vec<2>::Zero()));
  EXPECT_EQ(m.state, Contact::slip);
  // The friction load: the held tangential impulse's direction, capped at mu |j_n| = 0.8.
  EXPECT_LT((m.load - Vec<2>(-0.8, 0.0)).norm(), kTol);
}

TEST(ContactActiveSet, SlipFollowsTheNormalImpulseAndSticksWhenTheSlidingReverses) {
  Multiplier m;
  m.state = Contact::slip;
  m.load = Vec<2>(-0.8, 0.0);  // against sliding along +x
  // Still sliding along +x (the load opposes it), pushed harder (3): the load follows, 1.2.
  EXPECT_TRUE(m.pass(Vec<2>(-0.8, 3.0), Vec<2>(0.5, 0.0)));
  EXPECT_EQ(m.state, Contact::slip);
  EXPECT_LT((m.load - Vec<2>(-1.2, 0.0)).norm(), kTol);
  // The same push again: nothing to change.
  EXPECT_FALSE(m.pass(Vec<2>(-1.2, 3.0), Vec<2>(0.5, 0.0)));
  // The load reversed the sliding (the gap now moves along the load): the multiplier sticks
  // and the held impulse takes over from the load.
  EXPECT_TRUE(m.pass(Vec<2>(-1.2, 3.0), Vec<2>(-0.1, 0.0)));
  EXPECT_EQ(m.state, Contact::stick);
  EXPECT_EQ(m.load, Vec<2>::Zero());
}

TEST(ContactActiveSet, FrictionlessAndStickyMultipliersKeepTheirState) {
  // mu 0: a pushing multiplier stays in normal contact whatever its tangential impulse; a
  // sticky one (no friction coefficient, held in stick) stays stuck.
  Multiplier frictionless;
  frictionless.state = Contact::normal;
  EXPECT_FALSE(frictionless.pass(Vec<2>(5.0, 1.0), Vec<2>(1.0, 0.0), 0.0, true, Contact::normal));
  EXPECT_EQ(frictionless.state, Contact::normal);
  Multiplier sticky;
  EXPECT_FALSE(sticky.pass(Vec<2>(5.0, 1.0), Vec<2>(1.0, 0.0), 0.0));
  EXPECT_EQ(sticky.state, Contact::stick);
}

}  // namespace
}  // namespace mpm
