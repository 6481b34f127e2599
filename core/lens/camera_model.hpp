// Camera model: pinhole (fx, fy, cx, cy; no skew) with a lens-distortion model of the lens-model
// table (lens_models.hpp).
//
// Pixel convention: OpenCV's (pixel centres at integer coordinates), as cv::projectPoints,
// cv::undistort and cv::remap use.
//
// The parameter vector is [fx, fy, cx, cy, <distortion...>] in the model's order; callers see the
// vector, its names and the projection functions, never a model's internals, so adding a model
// changes nothing here (docs/architecture.md, "Adding a lens model").
#pragma once

#include <Eigen/Core>
#include <array>
#include <cmath>
#include <opencv2/core.hpp>
#include <string>
#include <vector>

#include "lens/lens_models.hpp"

namespace posecal {

class CameraModel {
 public:
  CameraModel() = default;
  // Throws Error(kInvalidArgument) if the parameter count does not match the model.
  CameraModel(int width, int height, LensModel model, std::vector<double> params);
  // A pinhole camera of the lens model, its distortion coefficients zero.
  static CameraModel pinhole(LensModel model, int width, int height, double fx, double fy, double cx, double cy);
  static CameraModel opencv5(int width, int height, double fx, double fy, double cx, double cy,
                             const std::array<double, 5>& k1_k2_p1_p2_k3);

  int width() const { return width_; }
  int height() const { return height_; }
  cv::Size size() const { return {width_, height_}; }
  LensModel lens_model() const { return model_; }
  int num_params() const { return static_cast<int>(params_.size()); }
  const std::vector<double>& params() const { return params_; }
  std::vector<double>& params() { return params_; }
  const std::vector<std::string>& param_names() const { return intrinsic_names(model_); }

  double fx() const { return params_[0]; }
  double fy() const { return params_[1]; }
  double cx() const { return params_[2]; }
  double cy() const { return params_[3]; }

  // OpenCV form of the model (for cv::projectPoints, cv::solvePnP ...).
  cv::Matx33d camera_matrix() const;
  std::vector<double> distortion_coefficients() const;
  // Builds a model from OpenCV's K and distortion vector: its length says the model (4 or 5:
  // opencv5, 4 with k3 = 0; 8, 12, 14: opencv8, opencv12, opencv14), as cv::projectPoints reads
  // it. Throws Error(kInvalidArgument) for another length, Error(kUnsupported) if K has skew.
  static CameraModel from_opencv(int width, int height, const cv::Matx33d& K,
                                 const std::vector<double>& dist);
  // The same for cv::fisheye's K and 4 coefficients (k1..k4): the fisheye model. Throws
  // Error(kInvalidArgument) for another count, Error(kUnsupported) if K has skew.
  static CameraModel from_opencv_fisheye(int width, int height, const cv::Matx33d& K,
                                         const std::vector<double>& dist);

  // The largest image a model may describe: kMaxImageSide pixels per side (below OpenCV's
  // cv::remap limit of 32767, SHRT_MAX) and kMaxImagePixels pixels (2^28, 268 MP; the largest
  // sensors sold have about 150 MP). Models from files, URIs and hosts are checked against it.
  static constexpr int kMaxImageSide = 30000;
  static constexpr long long kMaxImagePixels = 1LL << 28;

  // True if every parameter is finite, focal lengths are positive and the size is positive and
  // within kMaxImageSide / kMaxImagePixels.
  bool is_valid(std::string* why = nullptr) const;

  // Lens distortion of a normalised point.
  Eigen::Vector2d distort(const Eigen::Vector2d& xn) const;
  // Projects a camera-frame point; returns false if it is outside the model's field: not in front
  // of the camera (z <= 0), or for a ray model (the fisheye) beyond the angle from the axis where
  // the model folds (at most 180 degrees).
  bool project(const Eigen::Vector3d& p_cam, Eigen::Vector2d* uv) const;
  // As project(), with the analytic Jacobians d(uv)/d(p_cam) (2x3) and d(uv)/d(params) (2xN).
  bool project(const Eigen::Vector3d& p_cam, Eigen::Vector2d* uv, Eigen::Matrix<double, 2, 3>* J_p,
               Eigen::Matrix<double, 2, Eigen::Dynamic>* J_params) const;
  // Pixel -> normalised ray (x, y) with ray = (x, y, 1). Newton iteration on the distortion;
  // returns false where the model has no preimage (outside the model's valid region) or the
  // iteration does not converge.
  bool unproject(const Eigen::Vector2d& uv, Eigen::Vector2d* xn) const { return unproject(uv, xn, 0.0); }
  // The same, faster for many pixels: inside fold_free_r (from fold_free_radius() of this model)
  // the check that the distortion does not fold along the ray is skipped; the result is the same.
  bool unproject(const Eigen::Vector2d& uv, Eigen::Vector2d* xn, double fold_free_r) const;
  // Pixel -> unit ray in the camera frame, for every model and the whole field of view (a ray
  // model's rays may point 90 degrees or more from the axis, where unproject() fails).
  bool unproject_ray(const Eigen::Vector2d& uv, Eigen::Vector3d* ray) const;
  // The largest angle between a ray and the optical axis that the model projects: just below 90
  // degrees for the models of the plane Z = 1, up to 180 degrees for the fisheye.
  double max_ray_angle() const;
  // A radius in normalised coordinates inside which the distortion cannot fold (its Jacobian is
  // positive definite); 0 if none is known. A bound, not the exact fold radius.
  double fold_free_radius() const;
  // Per-pixel distortion magnitude in pixels: |p - K * unproject(p)| sampled at every `step`
  // pixels (cell (i, j) is pixel (j * step, i * step)). CV_32F; NaN where unproject fails. A ray
  // model's (the fisheye's) is its departure from the equidistant projection, f |theta_d - theta|,
  // NaN where unproject_ray fails.
  cv::Mat distortion_map(int step = 1) const;
  // Map of normalised rays for every pixel (CV_32FC2, NaN where unproject fails), optionally
  // supersampled: sample (i, j) of an n-times map is pixel ((j + 0.5) / n - 0.5, ...).
  cv::Mat ray_map(int supersample = 1) const;
  // The same as unit rays (CV_32FC3, NaN where unproject_ray fails): the whole field of view,
  // beyond 90 degrees from the axis for a ray model (the fisheye).
  cv::Mat direction_map(int supersample = 1) const;

 private:
  int width_ = 0;
  int height_ = 0;
  LensModel model_ = LensModel::kOpenCV5;
  std::vector<double> params_;
};

}  // namespace posecal
