#include "lens/geometry.hpp"

#include <cmath>
#include <limits>

namespace posecal {

Eigen::Matrix3d rotation_from_vector(const Eigen::Vector3d& r) {
  const double angle = r.norm();
  if (angle < 1e-15) return Eigen::Matrix3d::Identity();
  return Eigen::AngleAxisd(angle, r / angle).toRotationMatrix();
}

Eigen::Vector3d vector_from_rotation(const Eigen::Matrix3d& R) {
  const Eigen::AngleAxisd aa(R);
  return aa.axis() * aa.angle();
}

double rotation_angle_between(const Eigen::Matrix3d& A, const Eigen::Matrix3d& B) {
  return Eigen::AngleAxisd(A.transpose() * B).angle();
}

Eigen::Matrix3d Pose::R() const { return rotation_from_vector(r); }

Pose Pose::from_rotation(const Eigen::Matrix3d& R, const Eigen::Vector3d& t) {
  Pose p;
  p.r = vector_from_rotation(R);
  p.t = t;
  return p;
}

Pose Pose::inverse() const {
  const Eigen::Matrix3d Rt = R().transpose();
  return from_rotation(Rt, -Rt * t);
}

Pose Pose::compose(const Pose& other) const {
  const Eigen::Matrix3d Ra = R();
  return from_rotation(Ra * other.R(), Ra * other.t + t);
}

std::vector<cv::Point2d> project_points(const CameraModel& model, const Pose& T_cam_board,
                                        const std::vector<cv::Point3d>& board_points) {
  const Eigen::Matrix3d R = T_cam_board.R();
  std::vector<cv::Point2d> out;
  out.reserve(board_points.size());
  const double nan = std::numeric_limits<double>::quiet_NaN();
  for (const auto& P : board_points) {
    const Eigen::Vector3d pc = R * Eigen::Vector3d(P.x, P.y, P.z) + T_cam_board.t;
    Eigen::Vector2d uv;
    if (model.project(pc, &uv)) {
      out.emplace_back(uv.x(), uv.y());
    } else {
      out.emplace_back(nan, nan);
    }
  }
  return out;
}

}  // namespace posecal
