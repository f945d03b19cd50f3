// Shape functions: partition of unity, zero gradient sum and linear reproduction, in 1D/2D/3D.

#include <gtest/gtest.h>

#include <random>

#include "mpm/grid.hpp"

namespace mpm {
namespace {

template <int D, class Shape>
void check_consistency(double half_width) {
  Grid<D> grid;
  grid.resize(Vec<D>::Constant(-0.35), 0.25, Index<D>::Constant(12));
  std::mt19937 rng(42);
  std::uniform_real_distribution<double> u(0.3, 2.0);
  for (int trial = 0; trial < 200; ++trial) {
    Vec<D> x;
    for (int d = 0; d < D; ++d) x[d] = u(rng);
    const Stencil<D, Shape> st(grid, x, half_width);
    double sum = 0.0;
    Vec<D> grad_sum = Vec<D>::Zero();
    Vec<D> first_moment = Vec<D>::Zero();
    Mat<D> grad_moment = Mat<D>::Zero();
    st.for_each(grid, [&](int node, double N, const Vec<D>& dN, const Vec<D>& dx) {
      EXPECT_GE(N, -1e-15);
      const Vec<D> xi = grid.position(grid.multi(node));
      EXPECT_NEAR((xi - x - dx).norm(), 0.0, 1e-13);
      sum += N;
      grad_sum += dN;
      first_moment += N * xi;
      grad_moment += xi * dN.transpose();
    });
    // Round-off only: these identities hold exactly for all three kernels in the interior.
    EXPECT_NEAR(sum, 1.0, 1e-13);
    EXPECT_NEAR(grad_sum.norm(), 0.0, 1e-12);
    EXPECT_NEAR((first_moment - x).norm(), 0.0, 1e-13);
    EXPECT_NEAR((grad_moment - Mat<D>::Identity()).norm(), 0.0, 1e-12);
  }
}

TEST(ShapeFunctions, LinearIsConsistent) {
  check_consistency<1, LinearShape>(0.0);
  check_consistency<2, LinearShape>(0.0);
  check_consistency<3, LinearShape>(0.0);
}

TEST(ShapeFunctions, GimpIsConsistent) {
  for (double lp : {0.5, 0.25, 1.0 / 6.0, 0.125}) {
    check_consistency<1, GimpShape>(lp);
    check_consistency<2, GimpShape>(lp);
    check_consistency<3, GimpShape>(lp);
  }
}

TEST(ShapeFunctions, QuadraticBSplineIsConsistent) {
  check_consistency<1, BSpline2Shape>(0.0);
  check_consistency<2, BSpline2Shape>(0.0);
  check_consistency<3, BSpline2Shape>(0.0);
}

// The gradient returned is the derivative of the weight: central differences agree.
template <class Shape>
void check_gradient(double half_width) {
  std::mt19937 rng(7);
  std::uniform_real_distribution<double> u(2.0, 5.0);
  for (int trial = 0; trial < 500; ++trial) {
    const double x = u(rng), eps = 1e-6;
    int base, bp, bm;
    double w[3], dw[3], wp[3], dwp[3], wm[3], dwm[3];
    Shape::weights(x, half_width, base, w, dw);
    Shape::weights(x + eps, half_width, bp, wp, dwp);
    Shape::weights(x - eps, half_width, bm, wm, dwm);
    if (bp != base || bm != base) continue;  // stencil shifted between samples
    for (int k = 0; k < Shape::support; ++k) {
      EXPECT_NEAR(dw[k], (wp[k] - wm[k]) / (2 * eps), 1e-6) << "x=" << x << " k=" << k;
    }
  }
}

TEST(ShapeFunctions, GradientsMatchFiniteDifferences) {
  check_gradient<LinearShape>(0.0);
  check_gradient<GimpShape>(0.25);
  check_gradient<BSpline2Shape>(0.0);
}

}  // namespace
}  // namespace mpm
