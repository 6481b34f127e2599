#include "calib/metrics.hpp"

#include <Eigen/Dense>
#include <cmath>
#include <limits>

#include "calib/pose_estimation.hpp"
#include "common/error.hpp"
#include "lens/geometry.hpp"

namespace posecal {

TestError test_error(const CameraModel& estimate, const std::vector<Observation>& test_frames) {
  TestError out;
  double ss = 0;
  for (const auto& frame : test_frames) {
    Pose pose;
    double rms = 0;
    if (!estimate_pose(estimate, frame, &pose, &rms)) {
      ++out.frames_failed;
      continue;
    }
    ++out.frames_used;
    out.points += static_cast<int>(frame.size());
    ss += rms * rms * static_cast<double>(frame.size());
  }
  out.rms_px =
      out.points > 0 ? std::sqrt(ss / out.points) : std::numeric_limits<double>::quiet_NaN();
  return out;
}

namespace {

// Mean (or RMS) over a cols x rows grid, placed by pixel(i, j), of the distance between a pixel
// and the estimated projection of its true ray (the unit ray: a fisheye's reach beyond 90 degrees
// counts; pixels without a true ray, outside a fisheye's image circle, do not); NaN if no grid
// ray exists.
template <class Pixel>
double grid_error(const CameraModel& truth, const CameraModel& estimate, int cols, int rows, bool rms, Pixel pixel) {
  if (truth.size() != estimate.size()) {
    throw Error(ErrorCode::kInvalidArgument, "eps_gt: models have different image sizes");
  }
  double sum = 0;
  int n = 0;
  for (int j = 0; j < rows; ++j) {
    for (int i = 0; i < cols; ++i) {
      const Eigen::Vector2d p = pixel(i, j);
      Eigen::Vector3d ray;
      Eigen::Vector2d q;
      if (!truth.unproject_ray(p, &ray)) continue;
      if (!estimate.project(ray, &q)) continue;
      sum += rms ? (q - p).squaredNorm() : (q - p).norm();
      ++n;
    }
  }
  if (n == 0) return std::numeric_limits<double>::quiet_NaN();
  return rms ? std::sqrt(sum / n) : sum / n;
}

}  // namespace

double ground_truth_error(const CameraModel& truth, const CameraModel& estimate, int cols, int rows) {
  if (cols < 1 || rows < 1) throw Error(ErrorCode::kInvalidArgument, "eps_gt: grid must be >= 1x1");
  return grid_error(truth, estimate, cols, rows, false, [&](int i, int j) {
    return Eigen::Vector2d((i + 0.5) * truth.width() / cols - 0.5, (j + 0.5) * truth.height() / rows - 0.5);
  });
}

double ground_truth_error_edges(const CameraModel& truth, const CameraModel& estimate, int cols, int rows,
                                bool rms) {
  if (cols < 2 || rows < 2) throw Error(ErrorCode::kInvalidArgument, "eps_gt: edge grid must be >= 2x2");
  return grid_error(truth, estimate, cols, rows, rms, [&](int i, int j) {
    return Eigen::Vector2d(i * (truth.width() - 1.0) / (cols - 1), j * (truth.height() - 1.0) / (rows - 1));
  });
}

double ground_truth_error_aligned(const CameraModel& truth, const CameraModel& estimate, int cols,
                                  int rows, double* rotation_rad) {
  if (cols < 1 || rows < 1) throw Error(ErrorCode::kInvalidArgument, "eps_gt: grid must be >= 1x1");
  if (truth.size() != estimate.size()) {
    throw Error(ErrorCode::kInvalidArgument, "eps_gt: models have different image sizes");
  }
  std::vector<Eigen::Vector3d> rays;
  std::vector<Eigen::Vector2d> pixels;
  for (int j = 0; j < rows; ++j) {
    for (int i = 0; i < cols; ++i) {
      const Eigen::Vector2d p((i + 0.5) * truth.width() / cols - 0.5,
                              (j + 0.5) * truth.height() / rows - 0.5);
      Eigen::Vector3d ray;
      if (!truth.unproject_ray(p, &ray)) continue;
      rays.push_back(ray);
      pixels.push_back(p);
    }
  }
  const double nan = std::numeric_limits<double>::quiet_NaN();
  if (rays.empty()) return nan;
  // Gauss-Newton on R <- exp([dw]x) R; d(R ray)/d(dw) = -[R ray]x.
  Eigen::Matrix3d R = Eigen::Matrix3d::Identity();
  auto cost = [&](const Eigen::Matrix3d& Rc) {
    double ss = 0;
    for (size_t k = 0; k < rays.size(); ++k) {
      Eigen::Vector2d q;
      if (!estimate.project(Rc * rays[k], &q)) return std::numeric_limits<double>::infinity();
      ss += (q - pixels[k]).squaredNorm();
    }
    return ss;
  };
  double current = cost(R);
  for (int it = 0; it < 20 && std::isfinite(current); ++it) {
    Eigen::Matrix3d A = Eigen::Matrix3d::Zero();
    Eigen::Vector3d b = Eigen::Vector3d::Zero();
    for (size_t k = 0; k < rays.size(); ++k) {
      const Eigen::Vector3d Rr = R * rays[k];
      Eigen::Vector2d q;
      Eigen::Matrix<double, 2, 3> Jp;
      if (!estimate.project(Rr, &q, &Jp, nullptr)) continue;
      Eigen::Matrix3d skew;
      skew << 0, -Rr.z(), Rr.y(), Rr.z(), 0, -Rr.x(), -Rr.y(), Rr.x(), 0;
      const Eigen::Matrix<double, 2, 3> J = -Jp * skew;
      A += J.transpose() * J;
      b += J.transpose() * (q - pixels[k]);
    }
    const Eigen::Vector3d dw = -A.ldlt().solve(b);
    if (!dw.allFinite()) break;
    const Eigen::Matrix3d next = rotation_from_vector(dw) * R;
    const double c = cost(next);
    if (!(c < current)) break;
    R = next;
    const bool small = current - c < 1e-12 * current;
    current = c;
    if (small) break;
  }
  if (rotation_rad) *rotation_rad = Eigen::AngleAxisd(R).angle();
  double sum = 0;
  int n = 0;
  for (size_t k = 0; k < rays.size(); ++k) {
    Eigen::Vector2d q;
    if (!estimate.project(R * rays[k], &q)) continue;
    sum += (q - pixels[k]).norm();
    ++n;
  }
  return n > 0 ? sum / n : nan;
}

}  // namespace posecal
