// Rigid poses. Naming follows mrcal: T_cam_board maps board coordinates into the camera frame,
// p_cam = R * p_board + t; rt is its rotation-vector / translation pair (OpenCV's rvec, tvec).
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <opencv2/core.hpp>
#include <vector>

#include "lens/camera_model.hpp"

namespace posecal {

struct Pose {
  Eigen::Vector3d r = Eigen::Vector3d::Zero();  // rotation vector (axis * angle), radians
  Eigen::Vector3d t = Eigen::Vector3d::Zero();  // translation, metres

  Eigen::Matrix3d R() const;
  Eigen::Vector3d apply(const Eigen::Vector3d& p) const { return R() * p + t; }
  static Pose from_rotation(const Eigen::Matrix3d& R, const Eigen::Vector3d& t);
  Pose inverse() const;
  // this * other: first `other`, then this.
  Pose compose(const Pose& other) const;
  bool is_finite() const { return r.allFinite() && t.allFinite(); }
};

Eigen::Matrix3d rotation_from_vector(const Eigen::Vector3d& r);
Eigen::Vector3d vector_from_rotation(const Eigen::Matrix3d& R);
// Angle between two rotations, radians.
double rotation_angle_between(const Eigen::Matrix3d& A, const Eigen::Matrix3d& B);

// Projects board points through a pose and a camera model. Points behind the camera get NaN.
std::vector<cv::Point2d> project_points(const CameraModel& model, const Pose& T_cam_board,
                                        const std::vector<cv::Point3d>& board_points);

}  // namespace posecal
