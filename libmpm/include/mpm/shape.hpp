#pragma once
// Grid shape functions as tensor products of 1D kernels. Positions are in grid units
// (xg = (x - origin) / h); weights are returned per axis and gradients in 1/grid units, so the
// caller scales gradients by 1/h.
//
//   linear   : tent function, 2 nodes per axis.
//   gimp     : uniform GIMP (Bardenhagen & Kober 2004), particle half-width lp (grid units)
//              fixed at its initial value, 3 nodes per axis for lp <= 1/2.
//   bspline2 : quadratic B-spline (Steffen et al. 2008), 3 nodes per axis.

#include <cmath>
#include <string_view>

namespace mpm {

enum class ShapeKind { linear, gimp, bspline2 };

std::string_view to_string(ShapeKind kind);

struct LinearShape {
  static constexpr int support = 2;
  static void weights(double xg, double /*lp*/, int& base, double* w, double* dw) {
    base = static_cast<int>(std::floor(xg));
    const double fx = xg - base;
    w[0] = 1.0 - fx;
    w[1] = fx;
    dw[0] = -1.0;
    dw[1] = 1.0;
  }
};

struct GimpShape {
  static constexpr int support = 3;
  // 1D uGIMP kernel for node distance d = xg - x_i (h = 1), particle half-width lp.
  static void kernel(double d, double lp, double& w, double& dw) {
    const double a = std::abs(d);
    const double s = d < 0.0 ? -1.0 : 1.0;
    if (a < lp) {
      w = 1.0 - (d * d + lp * lp) / (2.0 * lp);
      dw = -d / lp;
    } else if (a < 1.0 - lp) {
      w = 1.0 - a;
      dw = -s;
    } else if (a < 1.0 + lp) {
      const double r = 1.0 + lp - a;
      w = r * r / (4.0 * lp);
      dw = -s * r / (2.0 * lp);
    } else {
      w = 0.0;
      dw = 0.0;
    }
  }
  static void weights(double xg, double lp, int& base, double* w, double* dw) {
    base = static_cast<int>(std::floor(xg - 0.5));
    for (int k = 0; k < 3; ++k) kernel(xg - (base + k), lp, w[k], dw[k]);
  }
};

struct BSpline2Shape {
  static constexpr int support = 3;
  /// D_p^-1 of APIC and MLS-MPM: sum_I N_I (x_I - x_p)(x_I - x_p)^T = h^2/4 I for this kernel.
  static double inverse_inertia(double inv_h) { return 4.0 * inv_h * inv_h; }
  static void weights(double xg, double /*lp*/, int& base, double* w, double* dw) {
    base = static_cast<int>(std::floor(xg - 0.5));
    const double fx = xg - base;  // in [0.5, 1.5)
    w[0] = 0.5 * (1.5 - fx) * (1.5 - fx);
    w[1] = 0.75 - (fx - 1.0) * (fx - 1.0);
    w[2] = 0.5 * (fx - 0.5) * (fx - 0.5);
    dw[0] = fx - 1.5;
    dw[1] = -2.0 * (fx - 1.0);
    dw[2] = fx - 0.5;
  }
};

/// Calls f(ShapeType{}) with the shape type for `kind`: the one place a runtime choice becomes a
/// compile-time kernel.
template <class F>
decltype(auto) dispatch_shape(ShapeKind kind, F&& f) {
  switch (kind) {
    case ShapeKind::linear:
      return f(LinearShape{});
    case ShapeKind::gimp:
      return f(GimpShape{});
    case ShapeKind::bspline2:
      break;
  }
  return f(BSpline2Shape{});
}

}  // namespace mpm
