// OpenCV's full lens model and its prefixes: rational radial distortion (k4 k5 k6 in the
// denominator), thin prism (s1..s4) and the tilted sensor (tau_x, tau_y), in OpenCV's order
//   k1 k2 p1 p2 k3 k4 k5 k6 s1 s2 s3 s4 tau_x tau_y
// so that the first 8, 12 or 14 coefficients are exactly the distortion vector cv::projectPoints,
// cv::undistort and cv::initUndistortRectifyMap take (CALIB_RATIONAL_MODEL, CALIB_THIN_PRISM_MODEL,
// CALIB_TILTED_MODEL). Three entries of the lens-model table (lens_models.hpp): opencv8,
// opencv12, opencv14; docs/math.md, "Rational, thin-prism and tilted-sensor models".
#pragma once

#include <Eigen/Core>
#include <array>
#include <cmath>

namespace posecal::lens {

inline constexpr std::array<const char*, 14> kOpenCVFullNames{
    "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6", "s1", "s2", "s3", "s4", "tau_x", "tau_y"};

// The model with OpenCV's first N coefficients, N = 8 (rational), 12 (and thin prism) or 14 (and
// tilted sensor).
template <int N>
struct OpenCVFull {
  static_assert(N == 8 || N == 12 || N == 14,
                "OpenCV's distortion vectors hold 8, 12 or 14 of these coefficients");
  static constexpr const char* kName = N == 8 ? "opencv8" : N == 12 ? "opencv12" : "opencv14";
  static constexpr int kNumDistortion = N;
  static constexpr std::array<const char*, N> kDistortionNames = [] {
    std::array<const char*, N> names{};
    for (int i = 0; i < N; ++i) names[i] = kOpenCVFullNames[i];
    return names;
  }();
  static constexpr int kOpenCVCoefficients = N;
  // Projects points of the plane Z = 1 (distort); not 3-D directions (see fisheye.hpp).
  static constexpr bool kRayModel = false;
  // k1 k2 p1 p2 k3 are always estimated; the coefficients after them are held while undetermined.
  static constexpr int kBaseDistortion = 5;
  static constexpr bool kThinPrism = N >= 12;
  static constexpr bool kTilted = N >= 14;

  // Distortion of a normalised point (x, y) = (X/Z, Y/Z), with the sensor tilt applied last as
  // OpenCV does: (xd, yd, w) ~ H(tau) (x', y', 1), H = projection onto the tilted sensor,
  //   H = [[c_x, 0, 0], [-s_x s_y, c_y, 0], [s_y, -c_y s_x, c_y c_x]]   (c_x = cos tau_x, ...),
  // which is OpenCV's computeTiltProjectionMatrix written out (docs/math.md). Templated for Jets.
  template <typename T>
  static void distort(const T* d, const T& x, const T& y, T* xd, T* yd) {
    const T x2 = x * x, y2 = y * y, xy = x * y;
    const T r2 = x2 + y2, r4 = r2 * r2, r6 = r4 * r2;
    const T radial =
        (T(1) + d[0] * r2 + d[1] * r4 + d[4] * r6) / (T(1) + d[5] * r2 + d[6] * r4 + d[7] * r6);
    T ux = x * radial + T(2) * d[2] * xy + d[3] * (r2 + T(2) * x2);
    T uy = y * radial + d[2] * (r2 + T(2) * y2) + T(2) * d[3] * xy;
    if constexpr (kThinPrism) {
      ux += d[8] * r2 + d[9] * r4;
      uy += d[10] * r2 + d[11] * r4;
    }
    if constexpr (kTilted) {
      using std::cos;
      using std::sin;
      const T cX = cos(d[12]), sX = sin(d[12]), cY = cos(d[13]), sY = sin(d[13]);
      const T h2 = sY * ux - cY * sX * uy + cY * cX;
      *xd = cX * ux / h2;
      *yd = (cY * uy - sX * sY * ux) / h2;
    } else {
      *xd = ux;
      *yd = uy;
    }
  }

  // Everything the derivatives need at one normalised point: the untilted distortion (ux, uy),
  // its Jacobian, the tilt's Jacobian at it and the final (xd, yd).
  struct Eval {
    double r2, r4, r6, num, den, radial;
    double ux, uy, xd, yd;
    Eigen::Matrix2d J0;  // d(ux, uy)/d(x, y)
    Eigen::Matrix2d Jt;  // d(xd, yd)/d(ux, uy) (identity without tilt)
    double cX, sX, cY, sY, h2;
  };

  [[gnu::always_inline]] static inline void evaluate(const double* d, double x, double y, Eval* e) {
    const double x2 = x * x, y2 = y * y, xy = x * y;
    e->r2 = x2 + y2, e->r4 = e->r2 * e->r2, e->r6 = e->r4 * e->r2;
    e->num = 1 + d[0] * e->r2 + d[1] * e->r4 + d[4] * e->r6;
    e->den = 1 + d[5] * e->r2 + d[6] * e->r4 + d[7] * e->r6;
    e->radial = e->num / e->den;
    const double dnum = d[0] + 2 * d[1] * e->r2 + 3 * d[4] * e->r4;  // d num / d r2
    const double dden = d[5] + 2 * d[6] * e->r2 + 3 * d[7] * e->r4;
    const double drad = (dnum * e->den - e->num * dden) / (e->den * e->den);  // d radial / d r2
    e->ux = x * e->radial + 2 * d[2] * xy + d[3] * (e->r2 + 2 * x2);
    e->uy = y * e->radial + d[2] * (e->r2 + 2 * y2) + 2 * d[3] * xy;
    e->J0(0, 0) = e->radial + 2 * x2 * drad + 2 * d[2] * y + 6 * d[3] * x;
    e->J0(0, 1) = 2 * xy * drad + 2 * d[2] * x + 2 * d[3] * y;
    e->J0(1, 0) = e->J0(0, 1);
    e->J0(1, 1) = e->radial + 2 * y2 * drad + 6 * d[2] * y + 2 * d[3] * x;
    if constexpr (kThinPrism) {
      e->ux += d[8] * e->r2 + d[9] * e->r4;
      e->uy += d[10] * e->r2 + d[11] * e->r4;
      const double ax = 2 * (d[8] + 2 * d[9] * e->r2), ay = 2 * (d[10] + 2 * d[11] * e->r2);
      e->J0(0, 0) += ax * x, e->J0(0, 1) += ax * y;
      e->J0(1, 0) += ay * x, e->J0(1, 1) += ay * y;
    }
    if constexpr (kTilted) {
      e->cX = std::cos(d[12]), e->sX = std::sin(d[12]), e->cY = std::cos(d[13]),
      e->sY = std::sin(d[13]);
      e->h2 = e->sY * e->ux - e->cY * e->sX * e->uy + e->cY * e->cX;
      e->xd = e->cX * e->ux / e->h2;
      e->yd = (e->cY * e->uy - e->sX * e->sY * e->ux) / e->h2;
      // d(h0 / h2, h1 / h2)/d(ux, uy) with h = H (ux, uy, 1).
      e->Jt(0, 0) = (e->cX - e->xd * e->sY) / e->h2;
      e->Jt(0, 1) = (e->xd * e->cY * e->sX) / e->h2;
      e->Jt(1, 0) = (-e->sX * e->sY - e->yd * e->sY) / e->h2;
      e->Jt(1, 1) = (e->cY + e->yd * e->cY * e->sX) / e->h2;
    } else {
      e->xd = e->ux, e->yd = e->uy;
      e->Jt.setIdentity();
    }
  }

  // The distortion and its 2x2 Jacobian d(xd, yd)/d(x, y) (unprojection's Newton steps).
  [[gnu::always_inline]] static inline void distort_jacobian(const double* dist, double x, double y,
                                                             double* xd, double* yd,
                                                             Eigen::Matrix2d* J) {
    Eval e;
    evaluate(dist, x, y, &e);
    *xd = e.xd, *yd = e.yd;
    if constexpr (kTilted) {
      *J = e.Jt * e.J0;
    } else {
      *J = e.J0;
    }
  }

  // Projection of a camera-frame point with d(u, v)/d(p_cam) and d(u, v)/d(fx fy cx cy k1 ...), a
  // 2x(4+N) column-major array; by hand (tests compare with central differences).
  [[gnu::always_inline]] static inline void project_jacobians(const double* q,
                                                              const Eigen::Vector3d& pc, double* u,
                                                              double* v,
                                                              Eigen::Matrix<double, 2, 3>* Jc,
                                                              double* Ji) {
    const double fx = q[0], fy = q[1];
    const double* d = q + 4;
    const double iz = 1.0 / pc.z();
    const double x = pc.x() * iz, y = pc.y() * iz;
    Eval e;
    evaluate(d, x, y, &e);
    *u = fx * e.xd + q[2];
    *v = fy * e.yd + q[3];
    const Eigen::Matrix2d Jxy = kTilted ? Eigen::Matrix2d(e.Jt * e.J0) : e.J0;
    (*Jc)(0, 0) = fx * Jxy(0, 0) * iz, (*Jc)(0, 1) = fx * Jxy(0, 1) * iz;
    (*Jc)(0, 2) = -fx * (Jxy(0, 0) * x + Jxy(0, 1) * y) * iz;
    (*Jc)(1, 0) = fy * Jxy(1, 0) * iz, (*Jc)(1, 1) = fy * Jxy(1, 1) * iz;
    (*Jc)(1, 2) = -fy * (Jxy(1, 0) * x + Jxy(1, 1) * y) * iz;
    // Column-major 2x(4+N): element (r, k) at Ji[2 k + r].
    Ji[0] = e.xd, Ji[1] = 0, Ji[2] = 0, Ji[3] = e.yd;
    Ji[4] = 1, Ji[5] = 0, Ji[6] = 0, Ji[7] = 1;
    // d(ux, uy)/d(coefficient), then through the tilt and the focal lengths.
    auto column = [&](int k, double dux, double duy) {
      const double a = e.Jt(0, 0) * dux + e.Jt(0, 1) * duy, b = e.Jt(1, 0) * dux + e.Jt(1, 1) * duy;
      Ji[2 * (4 + k)] = fx * a, Ji[2 * (4 + k) + 1] = fy * b;
    };
    const double iden = 1.0 / e.den, rden = e.radial * iden;  // d radial/d num, -d radial/d den
    column(0, x * e.r2 * iden, y * e.r2 * iden);
    column(1, x * e.r4 * iden, y * e.r4 * iden);
    column(2, 2 * x * y, e.r2 + 2 * y * y);
    column(3, e.r2 + 2 * x * x, 2 * x * y);
    column(4, x * e.r6 * iden, y * e.r6 * iden);
    column(5, -x * e.r2 * rden, -y * e.r2 * rden);
    column(6, -x * e.r4 * rden, -y * e.r4 * rden);
    column(7, -x * e.r6 * rden, -y * e.r6 * rden);
    if constexpr (kThinPrism) {
      column(8, e.r2, 0);
      column(9, e.r4, 0);
      column(10, 0, e.r2);
      column(11, 0, e.r4);
    }
    if constexpr (kTilted) {
      // h = H(tau) (ux, uy, 1); d(xd, yd)/d tau = (dh0 - xd dh2, dh1 - yd dh2) / h2.
      auto tau_column = [&](int k, double dh0, double dh1, double dh2) {
        Ji[2 * (4 + k)] = fx * (dh0 - e.xd * dh2) / e.h2;
        Ji[2 * (4 + k) + 1] = fy * (dh1 - e.yd * dh2) / e.h2;
      };
      tau_column(12, -e.sX * e.ux, -e.cX * e.sY * e.ux, -e.cY * e.cX * e.uy - e.cY * e.sX);
      tau_column(13, 0, -e.sX * e.cY * e.ux - e.sY * e.uy,
                 e.cY * e.ux + e.sY * e.sX * e.uy - e.sY * e.cX);
    }
  }

  // No bound is known for the rational and tilted forms: unprojection checks every solution
  // along its ray instead (CameraModel::fold_free_radius() documents 0 as "none known").
  static double fold_free_radius(const double*) { return 0.0; }
};

using OpenCV8 = OpenCVFull<8>;
using OpenCV12 = OpenCVFull<12>;
using OpenCV14 = OpenCVFull<14>;

}  // namespace posecal::lens
