// The pose of one board view with the intrinsics held fixed (PnP): used to warm-start new frames,
// to estimate the current board pose in the live loop, and by eps_test.
#include "calib/pose_estimation.hpp"

#include <ceres/ceres.h>
#include <ceres/rotation.h>

#include <Eigen/Dense>
#include <cmath>
#include <limits>
#include <opencv2/calib3d.hpp>
#include <optional>

namespace posecal {

namespace {

// The angular error of one ray: ray x (R P + t) / |R P + t| (its norm is the sine of the angle).
struct RayError {
  RayError(const Eigen::Vector3d& ray, const cv::Point3d& P) : ray_(ray), P_(P) {}
  template <typename T>
  bool operator()(const T* rt, T* e) const {
    const T P[3] = {T(P_.x), T(P_.y), T(P_.z)};
    T d[3];
    ceres::AngleAxisRotatePoint(rt, P, d);
    for (int i = 0; i < 3; ++i) d[i] += rt[3 + i];
    const T n = ceres::sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2]);
    e[0] = (T(ray_.y()) * d[2] - T(ray_.z()) * d[1]) / n;
    e[1] = (T(ray_.z()) * d[0] - T(ray_.x()) * d[2]) / n;
    e[2] = (T(ray_.x()) * d[1] - T(ray_.y()) * d[0]) / n;
    return true;
  }
  Eigen::Vector3d ray_;
  cv::Point3d P_;
};

}  // namespace

bool pose_from_rays(const std::vector<cv::Point3d>& object,
                    const std::vector<Eigen::Vector3d>& rays, Pose* T_cam_board, bool refine) {
  const size_t n = object.size();
  if (n < 4 || rays.size() != n) return false;
  // Board coordinates centred and scaled to unit mean distance: a well-conditioned fit.
  Eigen::Vector2d mean = Eigen::Vector2d::Zero();
  for (const cv::Point3d& P : object) {
    if (P.z != 0.0 || !std::isfinite(P.x) || !std::isfinite(P.y)) return false;
    mean += Eigen::Vector2d(P.x, P.y);
  }
  mean /= static_cast<double>(n);
  double spread = 0;
  for (const cv::Point3d& P : object) spread += (Eigen::Vector2d(P.x, P.y) - mean).norm();
  spread /= static_cast<double>(n);
  if (!(spread > 0)) return false;
  // ray x (H q) = 0 for q = ((x, y) - mean) / spread, 1): three rows per point, linear in H's
  // nine entries (row-major); H is the null vector of A^T A.
  Eigen::Matrix<double, 9, 9> AtA = Eigen::Matrix<double, 9, 9>::Zero();
  for (size_t i = 0; i < n; ++i) {
    const Eigen::Vector3d& r = rays[i];
    if (!r.allFinite()) return false;
    const Eigen::Vector3d q((object[i].x - mean.x()) / spread, (object[i].y - mean.y()) / spread,
                            1.0);
    Eigen::Matrix<double, 3, 9> rows = Eigen::Matrix<double, 3, 9>::Zero();
    // [r]x H q: row k of [r]x times H q, where (H q)_j = h_j . q.
    const Eigen::Matrix3d rx =
        (Eigen::Matrix3d() << 0, -r.z(), r.y(), r.z(), 0, -r.x(), -r.y(), r.x(), 0).finished();
    for (int k = 0; k < 3; ++k)
      for (int j = 0; j < 3; ++j) rows.block<1, 3>(k, 3 * j) = rx(k, j) * q.transpose();
    AtA.noalias() += rows.transpose() * rows;
  }
  const Eigen::SelfAdjointEigenSolver<Eigen::Matrix<double, 9, 9>> eig(AtA);
  if (eig.info() != Eigen::Success) return false;
  // The null space must be one-dimensional (points on a line leave two).
  if (!(eig.eigenvalues()(1) > 1e-12 * eig.eigenvalues()(8))) return false;
  Eigen::Matrix3d Hn;
  for (int j = 0; j < 3; ++j) Hn.row(j) = eig.eigenvectors().col(0).segment<3>(3 * j).transpose();
  // Back to board coordinates: q = N (x, y, 1).
  const Eigen::Matrix3d N = (Eigen::Matrix3d() << 1 / spread, 0, -mean.x() / spread, 0, 1 / spread,
                             -mean.y() / spread, 0, 0, 1)
                                .finished();
  Eigen::Matrix3d H = Hn * N;
  // The sign that puts the points along their rays, not opposite.
  double along = 0;
  for (size_t i = 0; i < n; ++i)
    along += rays[i].dot(H * Eigen::Vector3d(object[i].x, object[i].y, 1.0));
  if (along < 0) H = -H;
  const double scale = 0.5 * (H.col(0).norm() + H.col(1).norm());
  if (!(scale > 0)) return false;
  Eigen::Matrix3d M;
  M.col(0) = H.col(0) / scale;
  M.col(1) = H.col(1) / scale;
  M.col(2) = M.col(0).cross(M.col(1));
  const Eigen::JacobiSVD<Eigen::Matrix3d> svd(M, Eigen::ComputeFullU | Eigen::ComputeFullV);
  Eigen::Matrix3d R = svd.matrixU() * svd.matrixV().transpose();
  if (R.determinant() < 0) return false;
  Pose pose = Pose::from_rotation(R, H.col(2) / scale);
  if (!pose.is_finite()) return false;
  if (refine) {
    double rt[6] = {pose.r.x(), pose.r.y(), pose.r.z(), pose.t.x(), pose.t.y(), pose.t.z()};
    ceres::Problem problem;
    for (size_t i = 0; i < n; ++i)
      problem.AddResidualBlock(
          new ceres::AutoDiffCostFunction<RayError, 3, 6>(new RayError(rays[i], object[i])),
          nullptr, rt);
    ceres::Solver::Options options;
    options.max_num_iterations = 50;
    options.linear_solver_type = ceres::DENSE_QR;
    options.logging_type = ceres::SILENT;
    ceres::Solver::Summary summary;
    ceres::Solve(options, &problem, &summary);
    Pose refined;
    refined.r << rt[0], rt[1], rt[2];
    refined.t << rt[3], rt[4], rt[5];
    if (summary.IsSolutionUsable() && refined.is_finite()) pose = refined;
  }
  *T_cam_board = pose;
  return true;
}

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
  const bool ray_model = is_ray_model(model.lens_model());
  if (in.object.size() < 4 && !ray_model) return false;
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
  auto consider = [&](const Pose& p) {
    // A ray model sees boards beyond 90 degrees (z < 0); rms_of() is NaN where a point is
    // outside its field.
    if (!p.is_finite() || !(ray_model || p.t.z() > 0)) return;
    const double r = rms_of(p);
    if (std::isfinite(r) && r < best_rms) {
      best_rms = r;
      best = p;
    }
  };
  if (ray_model && planar) {
    std::vector<cv::Point3d> object;
    std::vector<Eigen::Vector3d> rays;
    for (size_t i = 0; i < frame.size(); ++i) {
      Eigen::Vector3d ray;
      if (!model.unproject_ray(Eigen::Vector2d(frame.image_points[i].x, frame.image_points[i].y),
                               &ray))
        continue;
      object.push_back(frame.board_points[i]);
      rays.push_back(ray);
    }
    Pose p;
    if (pose_from_rays(object, rays, &p)) consider(p);
  }
  const bool opencv_pnp = in.object.size() >= 4;  // a fisheye's board may lie beyond 90 degrees
  try {
    cv::Mat rvec, tvec;
    if (opencv_pnp && planar &&
        cv::solvePnP(in.object, in.image, K, dist, rvec, tvec, false, cv::SOLVEPNP_IPPE)) {
      consider(to_pose(rvec, tvec));
      cv::solvePnPRefineLM(in.object, in.image, K, dist, rvec, tvec);
      consider(to_pose(rvec, tvec));
    }
  } catch (const cv::Exception&) {
  }
  try {
    cv::Mat rvec, tvec;
    if (opencv_pnp &&
        cv::solvePnP(in.object, in.image, K, dist, rvec, tvec, false, cv::SOLVEPNP_ITERATIVE)) {
      consider(to_pose(rvec, tvec));
    }
  } catch (const cv::Exception&) {
  }
  if (!best) return false;
  if (rms_px) *rms_px = best_rms;
  *T_cam_board = *best;
  return true;
}

}  // namespace posecal
