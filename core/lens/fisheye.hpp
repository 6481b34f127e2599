// The Kannala-Brandt equidistant fisheye model with four coefficients, in OpenCV's cv::fisheye
// convention (and ROS's and Kalibr's "equidistant"):
//   theta = angle between the ray and the optical axis,
//   theta_d = theta (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 + k4 theta^8),
//   (xd, yd) = theta_d (X, Y) / |(X, Y)|,   (u, v) = (fx xd + cx, fy yd + cy).
// cv::fisheye computes theta = atan(|(X/Z, Y/Z)|) and so holds for Z > 0 only; here
// theta = atan2(|(X, Y)|, Z), the same in front of the camera and valid beyond 90 degrees from
// the axis (a 185-degree lens), up to max_theta(), where theta_d stops increasing. One entry of
// the lens-model table (lens_models.hpp); docs/math.md, "Fisheye model".
#pragma once

#include <Eigen/Core>
#include <algorithm>
#include <array>
#include <cmath>

namespace posecal::lens {

struct Fisheye {
  static constexpr const char* kName = "fisheye";
  static constexpr int kNumDistortion = 4;
  static constexpr std::array<const char*, kNumDistortion> kDistortionNames{"k1", "k2", "k3", "k4"};
  // Not one of OpenCV's pinhole distortion vectors: a file says "fisheye" by name.
  static constexpr int kOpenCVCoefficients = 0;
  // Projects 3-D directions, not points of the plane Z = 1 (see project_ray).
  static constexpr bool kRayModel = true;
  // k1 k2 are always estimated; k3 k4 are held while the keyframes do not determine them.
  static constexpr int kBaseDistortion = 2;

  // theta_d(theta) and d theta_d / d theta.
  template <typename T>
  static T distorted_angle(const T* k, const T& th) {
    const T t2 = th * th;
    return th * (T(1) + t2 * (k[0] + t2 * (k[1] + t2 * (k[2] + t2 * k[3]))));
  }
  static double distorted_angle_slope(const double* k, double th) {
    const double t2 = th * th;
    return 1 + t2 * (3 * k[0] + t2 * (5 * k[1] + t2 * (7 * k[2] + t2 * 9 * k[3])));
  }

  // A camera-frame direction (X, Y, Z) to the distorted normalised plane (xd, yd), so that
  // (u, v) = (fx xd + cx, fy yd + cy). Templated for Ceres' Jets. Near the axis (|(X, Y)| below
  // 1e-9 Z) the series theta_d / rho = (1 + (k1 - 1/3) (rho/Z)^2) / Z, exact to double precision,
  // avoids the square root's infinite derivative at 0.
  template <typename T>
  static void project_ray(const T* k, const T& X, const T& Y, const T& Z, T* xd, T* yd) {
    const T rho2 = X * X + Y * Y;
    T s;  // theta_d / rho
    if (rho2 > T(1e-18) * Z * Z || !(Z > T(0))) {
      using std::atan2;
      using std::sqrt;
      const T rho = sqrt(rho2);
      s = distorted_angle(k, atan2(rho, Z)) / rho;
    } else {
      const T iz = T(1) / Z;
      s = iz * (T(1) + (k[0] - T(1.0 / 3.0)) * rho2 * iz * iz);
    }
    *xd = s * X;
    *yd = s * Y;
  }

  // Distortion of a normalised point (x, y) = (X/Z, Y/Z) (Z > 0 only; see project_ray).
  template <typename T>
  static void distort(const T* k, const T& x, const T& y, T* xd, T* yd) {
    project_ray(k, x, y, T(1), xd, yd);
  }

  // The same with d(xd, yd)/d(x, y): the radial map (x, y) -> g(r) (x, y) / r, g(r) =
  // theta_d(atan r), has J = s I + (s' / r) (x, y)(x, y)^T, s = g / r.
  [[gnu::always_inline]] static inline void distort_jacobian(const double* k, double x, double y,
                                                             double* xd, double* yd,
                                                             Eigen::Matrix2d* J) {
    const double r2 = x * x + y * y;
    double s, ds_over_r;  // s = g / r, (ds/dr) / r
    if (r2 > 1e-12) {
      const double r = std::sqrt(r2), th = std::atan(r);
      const double g = distorted_angle(k, th);
      s = g / r;
      ds_over_r = (distorted_angle_slope(k, th) / (1 + r2) - s) / r2;
    } else {
      // s = 1 + (k1 - 1/3) r^2 + O(r^4)
      s = 1 + (k[0] - 1.0 / 3.0) * r2;
      ds_over_r = 2 * (k[0] - 1.0 / 3.0);
    }
    *xd = s * x, *yd = s * y;
    (*J)(0, 0) = s + ds_over_r * x * x;
    (*J)(0, 1) = (*J)(1, 0) = ds_over_r * x * y;
    (*J)(1, 1) = s + ds_over_r * y * y;
  }

  // Projection of a camera-frame point with d(u, v)/d(p_cam) and d(u, v)/d(fx fy cx cy k1..k4),
  // a 2x8 column-major array; by hand (tests compare with central differences). With
  // rho = |(X, Y)|, R^2 = rho^2 + Z^2, theta = atan2(rho, Z), s = theta_d / rho:
  //   d theta / d(X, Y, Z) = (Z X / (rho R^2), Z Y / (rho R^2), -rho / R^2),
  //   d s / d(X, Y) = (X, Y) a,  a = theta_d' Z / (rho^2 R^2) - theta_d / rho^3,
  //   d s / d Z = -theta_d' / R^2.
  [[gnu::always_inline]] static inline void project_jacobians(const double* q,
                                                              const Eigen::Vector3d& pc, double* u,
                                                              double* v,
                                                              Eigen::Matrix<double, 2, 3>* Jc,
                                                              double* Ji) {
    const double fx = q[0], fy = q[1];
    const double* k = q + 4;
    const double X = pc.x(), Y = pc.y(), Z = pc.z();
    const double rho2 = X * X + Y * Y, R2 = rho2 + Z * Z;
    double th, s, a, ds_dz, th_over_rho;
    if (rho2 > 1e-18 * Z * Z || !(Z > 0)) {
      const double rho = std::sqrt(rho2);
      th = std::atan2(rho, Z);
      const double g = distorted_angle(k, th), gp = distorted_angle_slope(k, th);
      s = g / rho;
      a = gp * Z / (rho2 * R2) - g / (rho2 * rho);
      ds_dz = -gp / R2;
      th_over_rho = th / rho;
    } else {
      const double iz = 1 / Z, c = k[0] - 1.0 / 3.0;
      th = std::sqrt(rho2) * iz;
      s = iz * (1 + c * rho2 * iz * iz);
      a = 2 * c * iz * iz * iz;
      ds_dz = -iz * iz;
      th_over_rho = iz;
    }
    const double xd = s * X, yd = s * Y;
    *u = fx * xd + q[2];
    *v = fy * yd + q[3];
    (*Jc)(0, 0) = fx * (s + a * X * X), (*Jc)(0, 1) = fx * a * X * Y, (*Jc)(0, 2) = fx * X * ds_dz;
    (*Jc)(1, 0) = fy * a * X * Y, (*Jc)(1, 1) = fy * (s + a * Y * Y), (*Jc)(1, 2) = fy * Y * ds_dz;
    // Column-major 2x8: element (r, k) at Ji[2 k + r]. d theta_d / d k_i = theta^(2i + 1).
    Ji[0] = xd, Ji[1] = 0, Ji[2] = 0, Ji[3] = yd;
    Ji[4] = 1, Ji[5] = 0, Ji[6] = 0, Ji[7] = 1;
    const double t2 = th * th;
    double p = th_over_rho * t2;  // theta^3 / rho
    for (int i = 0; i < 4; ++i, p *= t2)
      Ji[2 * (4 + i)] = fx * X * p, Ji[2 * (4 + i) + 1] = fy * Y * p;
  }

  // The angle from the axis up to which theta_d increases (theta_d' > 0 on [0, max_theta)), at
  // most pi: the model's field of view. Stepped out from 0 with a Lipschitz bound on theta_d', so
  // a bound, not the exact fold. With `limit`, stops there: max_theta(k, t) >= t says the model
  // holds up to t.
  static double max_theta(const double* k, double limit = M_PI) {
    auto lipschitz = [&](double t) {  // bound on |d theta_d' / d theta| over [0, t]
      const double t3 = t * t * t, t5 = t3 * t * t, t7 = t5 * t * t;
      return 6 * std::abs(k[0]) * t + 20 * std::abs(k[1]) * t3 + 42 * std::abs(k[2]) * t5 +
             72 * std::abs(k[3]) * t7;
    };
    constexpr double kMaxStep = 0.02, kMinStep = 1e-5;
    double t = 0;
    limit = std::min(limit, M_PI);
    while (t < limit) {
      const double slope = distorted_angle_slope(k, t);
      const double L = lipschitz(std::min(M_PI, t + kMaxStep));
      const double h = L > 0 ? std::min(kMaxStep, 0.5 * slope / L) : kMaxStep;
      if (!(h >= kMinStep)) break;
      t += h;
    }
    return std::min(t, limit);
  }

  // The angle theta in [0, max_theta) with theta_d(theta) = target (theta_d is increasing there),
  // by Newton steps kept inside a shrinking bracket. False if there is none.
  static bool undistort_angle(const double* k, double target, double max_th, double* theta) {
    if (!(target >= 0)) return false;
    if (target == 0) return *theta = 0, true;
    double lo = 0, hi = max_th;
    if (!(distorted_angle(k, hi) > target)) return false;
    double th = std::min(target, 0.5 * (lo + hi));
    for (int it = 0; it < 100; ++it) {
      const double f = distorted_angle(k, th) - target;
      if (std::abs(f) < 1e-15 * std::max(1.0, target)) break;
      (f > 0 ? hi : lo) = th;
      double next = th - f / distorted_angle_slope(k, th);
      if (!(next > lo && next < hi)) next = 0.5 * (lo + hi);
      if (next == th) break;
      th = next;
    }
    *theta = th;
    return true;
  }

  // Normalised coordinates: distortion folds nowhere below max_theta (J's eigenvalues are s and
  // theta_d' / (1 + r^2)), and the plane Z = 1 ends at 90 degrees.
  static double fold_free_radius(const double* k) {
    return std::tan(std::min(max_theta(k), 0.5 * M_PI * (1 - 1e-6)));
  }
};

}  // namespace posecal::lens
