// Unprojection (pixel -> ray) by Newton iteration on the distortion, and the per-pixel maps built
// on it (rays for the renderer, distortion magnitude for the C_Delta pose rule). docs/math.md.
#include <Eigen/Dense>
#include <cmath>
#include <limits>

#include "common/error.hpp"
#include "lens/camera_model.hpp"

namespace posecal {

namespace {

// The unit ray of a ray model whose distorted normalised point is (tx, ty).
// max_th: M::max_theta(dist), or 0 to compute it here.
template <class M>
bool invert_ray(const double* dist, double tx, double ty, Eigen::Vector3d* ray, double max_th = 0) {
  const double td = std::hypot(tx, ty);
  double theta;
  if (!M::undistort_angle(dist, td, max_th > 0 ? max_th : M::max_theta(dist), &theta)) return false;
  if (td == 0) {
    *ray = Eigen::Vector3d::UnitZ();
  } else {
    const double s = std::sin(theta) / td;
    *ray << s * tx, s * ty, std::cos(theta);
  }
  return true;
}

// Solves M::distort(x) = target by damped Newton from `x`. Rejects solutions where the
// distortion folds over (det J <= 0): there the model has no physical preimage. Inside
// `fold_free_r` (M::fold_free_radius()) the check along the ray is known to pass and is skipped.
// A ray model (the fisheye) inverts its angle instead: the solution is the ray at angle theta
// from the axis towards (tx, ty), in normalised coordinates if theta < 90 degrees.
template <class M>
bool invert_distortion(const double* dist, double tx, double ty, double* x, double* y, double fold_free_r = 0.0) {
  if constexpr (M::kRayModel) {
    // fold_free_r (M::fold_free_radius) is tan of the model's largest angle below 90 degrees.
    Eigen::Vector3d ray;
    if (!invert_ray<M>(dist, tx, ty, &ray, fold_free_r > 0 ? std::atan(fold_free_r) : 0.0) ||
        !(ray.z() > 1e-9))
      return false;
    *x = ray.x() / ray.z();
    *y = ray.y() / ray.z();
    return true;
  }
  double cx = *x, cy = *y;
  Eigen::Matrix2d J;
  double xd, yd;
  M::distort_jacobian(dist, cx, cy, &xd, &yd, &J);
  // Squared residuals (no hypot: this runs for every unprojected pixel).
  auto sq = [](double a, double b) { return a * a + b * b; };
  double err = sq(xd - tx, yd - ty);
  for (int it = 0; it < 40; ++it) {
    if (err < 1e-24) break;
    const double det = J.determinant();
    if (!(std::abs(det) > 1e-12)) return false;
    const Eigen::Vector2d step = J.inverse() * Eigen::Vector2d(xd - tx, yd - ty);
    double alpha = 1.0;
    bool improved = false;
    for (int ls = 0; ls < 20; ++ls, alpha *= 0.5) {
      const double nx = cx - alpha * step.x(), ny = cy - alpha * step.y();
      double nxd, nyd;
      Eigen::Matrix2d nJ;
      M::distort_jacobian(dist, nx, ny, &nxd, &nyd, &nJ);
      const double nerr = sq(nxd - tx, nyd - ty);
      if (nerr < err) {
        cx = nx;
        cy = ny;
        xd = nxd;
        yd = nyd;
        J = nJ;
        err = nerr;
        improved = true;
        break;
      }
    }
    if (!improved) break;
  }
  if (!(err < 1e-18) || !(J.determinant() > 0)) return false;
  // The physical preimage lies in the region around the optical axis where the distortion is
  // one-to-one: the Jacobian must stay positive along the whole ray from the centre. A solution
  // beyond a fold (e.g. k1 < 0 alone, past r = 1/sqrt(3|k1|)) can also have det J > 0.
  if (!(cx * cx + cy * cy < fold_free_r * fold_free_r)) {
    for (double f : {0.25, 0.5, 0.75}) {
      double ux, uy;
      Eigen::Matrix2d Jf;
      M::distort_jacobian(dist, f * cx, f * cy, &ux, &uy, &Jf);
      if (!(Jf.determinant() > 0)) return false;
    }
  }
  if (cx * tx + cy * ty < 0) return false;
  *x = cx;
  *y = cy;
  return true;
}

}  // namespace

double CameraModel::fold_free_radius() const {
  const double* dist = params_.data() + kNumPinholeParams;
  return with_lens_model(model_, [&](auto m) { return decltype(m)::fold_free_radius(dist); });
}

bool CameraModel::unproject(const Eigen::Vector2d& uv, Eigen::Vector2d* xn, double fold_free_r) const {
  const double tx = (uv.x() - cx()) / fx();
  const double ty = (uv.y() - cy()) / fy();
  double x = tx, y = ty;
  const double* dist = params_.data() + kNumPinholeParams;
  const bool ok = with_lens_model(
      model_, [&](auto m) { return invert_distortion<decltype(m)>(dist, tx, ty, &x, &y, fold_free_r); });
  if (!ok) return false;
  *xn << x, y;
  return true;
}

bool CameraModel::unproject_ray(const Eigen::Vector2d& uv, Eigen::Vector3d* ray) const {
  const double tx = (uv.x() - cx()) / fx();
  const double ty = (uv.y() - cy()) / fy();
  const double* dist = params_.data() + kNumPinholeParams;
  return with_lens_model(model_, [&](auto m) {
    using M = decltype(m);
    if constexpr (M::kRayModel) {
      return invert_ray<M>(dist, tx, ty, ray);
    } else {
      double x = tx, y = ty;
      if (!invert_distortion<M>(dist, tx, ty, &x, &y)) return false;
      *ray = Eigen::Vector3d(x, y, 1).normalized();
      return true;
    }
  });
}

cv::Mat CameraModel::ray_map(int supersample) const {
  if (supersample < 1) throw Error(ErrorCode::kInvalidArgument, "supersample must be >= 1");
  const int W = width_ * supersample, H = height_ * supersample;
  cv::Mat map(H, W, CV_32FC2);
  const double* dist = params_.data() + kNumPinholeParams;
  const float nan = std::numeric_limits<float>::quiet_NaN();
  const double fold_free_r = fold_free_radius();
  with_lens_model(model_, [&](auto m) {
    using M = decltype(m);
    for (int i = 0; i < H; ++i) {
      auto* row = map.ptr<cv::Vec2f>(i);
      const double v = (i + 0.5) / supersample - 0.5;
      const double ty = (v - cy()) / fy();
      // Warm start from the left neighbour: the map is smooth, so Newton needs 1-2 steps.
      double x = (-0.5 / supersample - cx()) / fx(), y = ty;
      bool have_prev = false;
      for (int j = 0; j < W; ++j) {
        const double u = (j + 0.5) / supersample - 0.5;
        const double tx = (u - cx()) / fx();
        double sx = have_prev ? x : tx, sy = have_prev ? y : ty;
        bool ok = invert_distortion<M>(dist, tx, ty, &sx, &sy, fold_free_r);
        if (!ok && have_prev) {
          sx = tx;
          sy = ty;
          ok = invert_distortion<M>(dist, tx, ty, &sx, &sy, fold_free_r);
        }
        if (ok) {
          row[j] = cv::Vec2f(static_cast<float>(sx), static_cast<float>(sy));
          x = sx;
          y = sy;
          have_prev = true;
        } else {
          row[j] = cv::Vec2f(nan, nan);
          have_prev = false;
        }
      }
    }
  });
  return map;
}

cv::Mat CameraModel::direction_map(int supersample) const {
  if (supersample < 1) throw Error(ErrorCode::kInvalidArgument, "supersample must be >= 1");
  if (!is_ray_model(model_)) {
    // The plane's rays, normalised.
    const cv::Mat plane = ray_map(supersample);
    cv::Mat map(plane.size(), CV_32FC3);
    for (int i = 0; i < plane.rows; ++i) {
      const auto* in = plane.ptr<cv::Vec2f>(i);
      auto* out = map.ptr<cv::Vec3f>(i);
      for (int j = 0; j < plane.cols; ++j) {
        const float n = std::sqrt(in[j][0] * in[j][0] + in[j][1] * in[j][1] + 1.0f);
        out[j] = cv::Vec3f(in[j][0] / n, in[j][1] / n, 1.0f / n);  // NaN stays NaN
      }
    }
    return map;
  }
  const int W = width_ * supersample, H = height_ * supersample;
  cv::Mat map(H, W, CV_32FC3);
  const double* dist = params_.data() + kNumPinholeParams;
  const float nan = std::numeric_limits<float>::quiet_NaN();
  with_lens_model(model_, [&](auto m) {
    using M = decltype(m);
    if constexpr (M::kRayModel) {
      const double max_th = M::max_theta(dist);
      for (int i = 0; i < H; ++i) {
        auto* row = map.ptr<cv::Vec3f>(i);
        const double ty = ((i + 0.5) / supersample - 0.5 - cy()) / fy();
        for (int j = 0; j < W; ++j) {
          const double tx = ((j + 0.5) / supersample - 0.5 - cx()) / fx();
          Eigen::Vector3d ray;
          row[j] = invert_ray<M>(dist, tx, ty, &ray, max_th) ? cv::Vec3f(ray.x(), ray.y(), ray.z())
                                                             : cv::Vec3f(nan, nan, nan);
        }
      }
    }
  });
  return map;
}

cv::Mat CameraModel::distortion_map(int step) const {
  if (step < 1) throw Error(ErrorCode::kInvalidArgument, "distortion map step must be >= 1");
  const int rows = (height_ + step - 1) / step, cols = (width_ + step - 1) / step;
  cv::Mat map(rows, cols, CV_32F);
  const double* dist = params_.data() + kNumPinholeParams;
  const double fold_free_r = fold_free_radius();
  with_lens_model(model_, [&](auto m) {
    using M = decltype(m);
    if constexpr (M::kRayModel) {
      // A ray model's distortion is its departure from the equidistant projection (theta_d =
      // theta), where its coefficients act: f (theta_d - theta) along the radius, over the whole
      // field of view (the displacement from a pinhole has no meaning beyond 90 degrees).
      const double max_th = M::max_theta(dist);
      const float nan = std::numeric_limits<float>::quiet_NaN();
      for (int i = 0; i < rows; ++i) {
        const double ty = (i * step - cy()) / fy();
        for (int j = 0; j < cols; ++j) {
          const double tx = (j * step - cx()) / fx();
          const double td = std::hypot(tx, ty);
          double theta;
          if (!M::undistort_angle(dist, td, max_th, &theta)) {
            map.at<float>(i, j) = nan;
            continue;
          }
          const double scale = td > 0 ? std::abs(1.0 - theta / td) : 0.0;
          map.at<float>(i, j) = static_cast<float>(std::hypot(fx() * tx, fy() * ty) * scale);
        }
      }
      return;
    }
    // Row start of the previous row, for the next row's warm start.
    bool have_above = false;
    double ax = 0, ay = 0;
    for (int i = 0; i < rows; ++i) {
      const double ty = (i * step - cy()) / fy();
      // Warm start (the map is smooth): the left neighbours' solutions extrapolated linearly, or
      // the one left neighbour, or for the first cell the row above's; Newton then needs one or
      // two steps.
      int have_prev = 0;
      double px = 0, py = 0, ppx = 0, ppy = 0;
      for (int j = 0; j < cols; ++j) {
        const double tx = (j * step - cx()) / fx();
        double x = tx, y = ty;
        if (have_prev >= 2) {
          x = 2 * px - ppx, y = 2 * py - ppy;
        } else if (have_prev == 1) {
          x = px, y = py;
        } else if (j == 0 && have_above) {
          x = ax, y = ay + step / fy();
        }
        bool ok = invert_distortion<M>(dist, tx, ty, &x, &y, fold_free_r);
        if (!ok && (x != tx || y != ty)) {  // warm-started: retry from the pinhole ray
          x = tx;
          y = ty;
          ok = invert_distortion<M>(dist, tx, ty, &x, &y, fold_free_r);
        }
        if (j == 0) have_above = ok, ax = x, ay = y;
        if (!ok) {
          map.at<float>(i, j) = std::numeric_limits<float>::quiet_NaN();
          have_prev = 0;
          continue;
        }
        ppx = px, ppy = py;
        px = x, py = y;
        ++have_prev;
        const double ex = fx() * (x - tx), ey = fy() * (y - ty);
        map.at<float>(i, j) = static_cast<float>(std::sqrt(ex * ex + ey * ey));
      }
    }
  });
  return map;
}

}  // namespace posecal
