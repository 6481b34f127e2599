// OpenCV's 5-coefficient Brown-Conrady lens model (paper eq. 2), in OpenCV's order k1 k2 p1 p2 k3,
// as cv::projectPoints, cv::undistort and cv::initUndistortRectifyMap use it. One entry of the
// lens-model table (lens_models.hpp); docs/math.md, "Camera model".
#pragma once

#include <Eigen/Core>
#include <algorithm>
#include <array>
#include <cmath>

namespace posecal::lens {

struct OpenCV5 {
  static constexpr const char* kName = "opencv5";
  static constexpr int kNumDistortion = 5;
  static constexpr std::array<const char*, kNumDistortion> kDistortionNames{"k1", "k2", "p1", "p2", "k3"};
  // Length of OpenCV's distortion vector that holds exactly this model (0: not an OpenCV vector).
  static constexpr int kOpenCVCoefficients = 5;
  // Projects points of the plane Z = 1 (distort); not 3-D directions (see fisheye.hpp).
  static constexpr bool kRayModel = false;
  // k1 k2 p1 p2 k3 are always estimated; the coefficients after them are held while undetermined.
  static constexpr int kBaseDistortion = 5;

  // Distortion of a normalised point (x, y) = (X/Z, Y/Z). Templated for Ceres' Jets.
  template <typename T>
  static void distort(const T* dist, const T& x, const T& y, T* xd, T* yd) {
    const T& k1 = dist[0];
    const T& k2 = dist[1];
    const T& p1 = dist[2];
    const T& p2 = dist[3];
    const T& k3 = dist[4];
    const T x2 = x * x, y2 = y * y, xy = x * y;
    const T r2 = x2 + y2;
    const T radial = T(1) + r2 * (k1 + r2 * (k2 + r2 * k3));    // paper eq. 2a
    *xd = x * radial + T(2) * p1 * xy + p2 * (r2 + T(2) * x2);  // paper eq. 2b
    *yd = y * radial + p1 * (r2 + T(2) * y2) + T(2) * p2 * xy;
  }

  // The distortion and its 2x2 Jacobian d(xd, yd)/d(x, y) (unprojection's Newton steps).
  [[gnu::always_inline]] static inline void distort_jacobian(const double* dist, double x, double y, double* xd,
                                                             double* yd, Eigen::Matrix2d* J) {
    const double k1 = dist[0], k2 = dist[1], p1 = dist[2], p2 = dist[3], k3 = dist[4];
    const double x2 = x * x, y2 = y * y, xy = x * y, r2 = x2 + y2;
    const double radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3));
    const double dradial_dr2 = k1 + r2 * (2 * k2 + 3 * k3 * r2);
    *xd = x * radial + 2 * p1 * xy + p2 * (r2 + 2 * x2);
    *yd = y * radial + p1 * (r2 + 2 * y2) + 2 * p2 * xy;
    (*J)(0, 0) = radial + 2 * x2 * dradial_dr2 + 2 * p1 * y + 6 * p2 * x;
    (*J)(0, 1) = 2 * xy * dradial_dr2 + 2 * p1 * x + 2 * p2 * y;
    (*J)(1, 0) = 2 * xy * dradial_dr2 + 2 * p1 * x + 2 * p2 * y;
    (*J)(1, 1) = radial + 2 * y2 * dradial_dr2 + 6 * p1 * y + 2 * p2 * x;
  }

  // Projection of a camera-frame point with its derivatives: Jc = d(u, v)/d(p_cam) and
  // Ji = d(u, v)/d(fx fy cx cy k1 k2 p1 p2 k3), a 2x9 column-major array (Eigen's layout). By
  // hand, a few times faster than forward-mode Jets; tests compare it with central differences.
  [[gnu::always_inline]] static inline void project_jacobians(const double* q, const Eigen::Vector3d& pc, double* u,
                                                              double* v, Eigen::Matrix<double, 2, 3>* Jc, double* Ji) {
    const double fx = q[0], fy = q[1], k1 = q[4], k2 = q[5], p1 = q[6], p2 = q[7], k3 = q[8];
    const double iz = 1.0 / pc.z();
    const double x = pc.x() * iz, y = pc.y() * iz;
    const double x2 = x * x, y2 = y * y, xy = x * y, r2 = x2 + y2, r4 = r2 * r2, r6 = r4 * r2;
    const double radial = 1 + k1 * r2 + k2 * r4 + k3 * r6;
    const double dradial = k1 + 2 * k2 * r2 + 3 * k3 * r4;  // d radial / d r2
    const double xd = x * radial + 2 * p1 * xy + p2 * (r2 + 2 * x2);
    const double yd = y * radial + p1 * (r2 + 2 * y2) + 2 * p2 * xy;
    *u = fx * xd + q[2];
    *v = fy * yd + q[3];
    // d(xd, yd)/d(x, y)
    const double a = radial + 2 * x2 * dradial + 2 * p1 * y + 6 * p2 * x;
    const double b = 2 * xy * dradial + 2 * p1 * x + 2 * p2 * y;
    const double d = radial + 2 * y2 * dradial + 6 * p1 * y + 2 * p2 * x;
    // d(x, y)/d(p_cam) = [[1/z, 0, -x/z], [0, 1/z, -y/z]]
    (*Jc)(0, 0) = fx * a * iz, (*Jc)(0, 1) = fx * b * iz, (*Jc)(0, 2) = -fx * (a * x + b * y) * iz;
    (*Jc)(1, 0) = fy * b * iz, (*Jc)(1, 1) = fy * d * iz, (*Jc)(1, 2) = -fy * (b * x + d * y) * iz;
    // Column-major 2x9: element (r, k) at Ji[2 k + r].
    const double J[2][9] = {{xd, 0, 1, 0, fx * x * r2, fx * x * r4, fx * 2 * xy, fx * (r2 + 2 * x2), fx * x * r6},
                            {0, yd, 0, 1, fy * y * r2, fy * y * r4, fy * (r2 + 2 * y2), fy * 2 * xy, fy * y * r6}};
    for (int k = 0; k < 9; ++k) Ji[2 * k] = J[0][k], Ji[2 * k + 1] = J[1][k];
  }

  // A radius (normalised coordinates) inside which the distortion's Jacobian is positive
  // definite, so it cannot fold. J = A + T with A = radial I + 2 radial' v v^T (v = (x, y),
  // radial' = d radial / d r^2; eigenvalues radial and radial + 2 r^2 radial') and the symmetric
  // tangential part T, |T| <= c r (Frobenius norm), so by Weyl's inequality J > 0 wherever
  // min(radial, radial + 2 r^2 radial') > c r. That holds on [0, r] for the r found by stepping
  // out with a Lipschitz bound on both polynomials (docs/math.md).
  static double fold_free_radius(const double* dist) {
    const double k1 = dist[0], k2 = dist[1], p1 = std::abs(dist[2]), p2 = std::abs(dist[3]), k3 = dist[4];
    const double t11 = 2 * p1 + 6 * p2, t12 = 2 * p1 + 2 * p2, t22 = 6 * p1 + 2 * p2;
    const double c = std::sqrt(t11 * t11 + 2 * t12 * t12 + t22 * t22);
    auto lower = [&](double r) {  // min of the two eigenvalue bounds at r
      const double r2 = r * r, r4 = r2 * r2, r6 = r4 * r2;
      return std::min(1 + k1 * r2 + k2 * r4 + k3 * r6, 1 + 3 * k1 * r2 + 5 * k2 * r4 + 7 * k3 * r6) - c * r;
    };
    auto lipschitz = [&](double r) {  // bound on |d lower / dr| over [0, r]
      const double r3 = r * r * r, r5 = r3 * r * r;
      return 6 * std::abs(k1) * r + 20 * std::abs(k2) * r3 + 42 * std::abs(k3) * r5 + c;
    };
    // Adaptive steps: lower > 0 on [r, r + h] if h < lower(r) / L, L bounding the slope there.
    constexpr double kMaxStep = 0.05, kMinStep = 1e-4, kMax = 4.0;
    double r = 0;
    while (r < kMax) {
      const double h = std::min(kMaxStep, 0.5 * lower(r) / lipschitz(r + kMaxStep));
      if (!(h >= kMinStep)) break;
      r += h;
    }
    return std::min(r, kMax);
  }
};

}  // namespace posecal::lens
