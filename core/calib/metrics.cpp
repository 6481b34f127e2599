#include "calib/metrics.hpp"

#include <cmath>
#include <limits>

#include "calib/pose_estimation.hpp"
#include "common/error.hpp"

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
// and the estimated projection of its true ray; NaN if no grid ray exists.
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
      Eigen::Vector2d xn, q;
      if (!truth.unproject(p, &xn)) continue;
      if (!estimate.project(Eigen::Vector3d(xn.x(), xn.y(), 1.0), &q)) continue;
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

}  // namespace posecal
