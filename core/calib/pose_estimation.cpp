// The pose of one board view with the intrinsics held fixed (PnP): used to warm-start new frames,
// to estimate the current board pose in the live loop, and by eps_test.
#include "calib/pose_estimation.hpp"

#include <cmath>
#include <limits>
#include <opencv2/calib3d.hpp>
#include <optional>

namespace posecal {

PnPInput pnp_input(const CameraModel& model, const std::vector<cv::Point3d>& object,
                   const std::vector<cv::Point2d>& image) {
  PnPInput in;
  if (opencv_coefficients(model.lens_model()) > 0) {
    in.K = cv::Mat(model.camera_matrix());
    in.dist = model.distortion_coefficients();
    in.object = object;
    in.image = image;
    return in;
  }
  in.K = cv::Mat::eye(3, 3, CV_64F);
  for (size_t i = 0; i < object.size() && i < image.size(); ++i) {
    Eigen::Vector2d xn;
    if (!model.unproject(Eigen::Vector2d(image[i].x, image[i].y), &xn)) continue;
    in.object.push_back(object[i]);
    in.image.emplace_back(xn.x(), xn.y());
  }
  return in;
}

bool estimate_pose(const CameraModel& model, const Observation& frame, Pose* T_cam_board,
                   double* rms_px) {
  if (frame.size() < 4 || frame.image_points.size() != frame.board_points.size()) return false;
  const PnPInput in = pnp_input(model, frame.board_points, frame.image_points);
  if (in.object.size() < 4) return false;
  const cv::Mat& K = in.K;
  const std::vector<double>& dist = in.dist;
  auto rms_of = [&](const Pose& p) {
    const auto proj = project_points(model, p, frame.board_points);
    double ss = 0;
    for (size_t i = 0; i < proj.size(); ++i) {
      const cv::Point2d d = proj[i] - frame.image_points[i];
      ss += d.dot(d);
    }
    return std::sqrt(ss / static_cast<double>(proj.size()));
  };
  auto to_pose = [](const cv::Mat& rvec, const cv::Mat& tvec) {
    Pose p;
    p.r << rvec.at<double>(0), rvec.at<double>(1), rvec.at<double>(2);
    p.t << tvec.at<double>(0), tvec.at<double>(1), tvec.at<double>(2);
    return p;
  };
  // Candidates: for planar targets IPPE's analytic solution refined by Levenberg-Marquardt, and
  // OpenCV's iterative solver. Either alone sometimes fails: the iterative one can settle in the
  // mirrored minimum of a tilted board (seen: 21 px test error for a 1 px calibration), the
  // refinement can diverge on a few corners at the border (seen: 18865 px with 7 corners). The
  // pose with the lower reprojection error wins.
  bool planar = true;
  for (const auto& P : in.object) planar = planar && P.z == 0.0;
  std::optional<Pose> best;
  double best_rms = std::numeric_limits<double>::infinity();
  auto consider = [&](const cv::Mat& rvec, const cv::Mat& tvec) {
    const Pose p = to_pose(rvec, tvec);
    if (!p.is_finite() || !(p.t.z() > 0)) return;
    const double r = rms_of(p);
    if (std::isfinite(r) && r < best_rms) {
      best_rms = r;
      best = p;
    }
  };
  try {
    cv::Mat rvec, tvec;
    if (planar &&
        cv::solvePnP(in.object, in.image, K, dist, rvec, tvec, false, cv::SOLVEPNP_IPPE)) {
      consider(rvec, tvec);
      cv::solvePnPRefineLM(in.object, in.image, K, dist, rvec, tvec);
      consider(rvec, tvec);
    }
  } catch (const cv::Exception&) {
  }
  try {
    cv::Mat rvec, tvec;
    if (cv::solvePnP(in.object, in.image, K, dist, rvec, tvec, false, cv::SOLVEPNP_ITERATIVE)) {
      consider(rvec, tvec);
    }
  } catch (const cv::Exception&) {
  }
  if (!best) return false;
  if (rms_px) *rms_px = best_rms;
  *T_cam_board = *best;
  return true;
}

}  // namespace posecal
