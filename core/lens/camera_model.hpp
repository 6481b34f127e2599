// Camera model: pinhole (fx, fy, cx, cy; no skew) with a lens-distortion model.
//
// Pixel convention: OpenCV's (pixel centres at integer coordinates), as cv::projectPoints,
// cv::undistort and cv::remap use.
//
// The parameter vector is [fx, fy, cx, cy, <distortion...>]. The only lens model so far is
// OpenCV's 5-coefficient Brown-Conrady model, in OpenCV order k1, k2, p1, p2, k3 (paper eq. 2).
// A richer model (rational k4..k6, thin prism, fisheye) is added by extending LensModel, the
// table in camera_model.cpp and the switch in project_generic(); callers only see the parameter
// vector, its names and the projection functions, so they do not change.
#pragma once

#include <Eigen/Core>
#include <array>
#include <cmath>
#include <opencv2/core.hpp>
#include <string>
#include <vector>

namespace posecal {

enum class LensModel {
  kOpenCV5 = 0,  // k1 k2 p1 p2 k3
};

// Number of pinhole parameters that precede the distortion coefficients.
inline constexpr int kNumPinholeParams = 4;
// Upper bound on the parameter count of any lens model; sizes fixed arrays.
inline constexpr int kMaxIntrinsics = 18;

int num_distortion_params(LensModel model);
inline int num_intrinsics(LensModel model) {
  return kNumPinholeParams + num_distortion_params(model);
}
const std::vector<std::string>& intrinsic_names(LensModel model);
const char* lens_model_name(LensModel model);

// Applies the lens distortion to a normalised image point (x, y) = (X/Z, Y/Z).
// `dist` points at the distortion coefficients (params + 4). Templated for Ceres' Jets.
template <typename T>
inline void distort_generic(LensModel model, const T* dist, const T& x, const T& y, T* xd, T* yd) {
  switch (model) {
    case LensModel::kOpenCV5: {
      const T& k1 = dist[0];
      const T& k2 = dist[1];
      const T& p1 = dist[2];
      const T& p2 = dist[3];
      const T& k3 = dist[4];
      const T x2 = x * x, y2 = y * y, xy = x * y;
      const T r2 = x2 + y2;
      const T radial = T(1) + r2 * (k1 + r2 * (k2 + r2 * k3));    // paper eq. 2a
      *xd = x * radial + T(2) * p1 * xy + p2 * (r2 + T(2) * x2);  // paper eq. 2b
      *yd = y * radial + p1 * (r2 + T(2) * y2) + T(2) * p2 * xy;
      return;
    }
  }
  *xd = x;
  *yd = y;
}

// Projects a camera-frame point to pixels: pi(P) = K * Delta(P / Z) (paper eq. 1).
template <typename T>
inline void project_generic(LensModel model, const T* params, const T* p_cam, T* uv) {
  const T x = p_cam[0] / p_cam[2];
  const T y = p_cam[1] / p_cam[2];
  T xd, yd;
  distort_generic(model, params + kNumPinholeParams, x, y, &xd, &yd);
  uv[0] = params[0] * xd + params[2];
  uv[1] = params[1] * yd + params[3];
}

class CameraModel {
 public:
  CameraModel() = default;
  // Throws Error(kInvalidArgument) if the parameter count does not match the model.
  CameraModel(int width, int height, LensModel model, std::vector<double> params);
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
  // Builds a model from OpenCV's K and distortion vector (4, 5, 8, 12 or 14 coefficients;
  // only models this build knows are accepted: coefficients beyond k3 must be zero).
  static CameraModel from_opencv(int width, int height, const cv::Matx33d& K,
                                 const std::vector<double>& dist);

  // True if every parameter is finite, focal lengths are positive and the size is positive.
  bool is_valid(std::string* why = nullptr) const;

  // Lens distortion of a normalised point.
  Eigen::Vector2d distort(const Eigen::Vector2d& xn) const;
  // Projects a camera-frame point; returns false if it is not in front of the camera (z <= 0).
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
  // A radius in normalised coordinates inside which the distortion cannot fold (its Jacobian is
  // positive definite); 0 if none is known. A bound, not the exact fold radius.
  double fold_free_radius() const;
  // Per-pixel distortion magnitude in pixels: |p - K * unproject(p)| sampled at every `step`
  // pixels (cell (i, j) is pixel (j * step, i * step)). CV_32F; NaN where unproject fails.
  cv::Mat distortion_map(int step = 1) const;
  // Map of normalised rays for every pixel (CV_32FC2, NaN where unproject fails), optionally
  // supersampled: sample (i, j) of an n-times map is pixel ((j + 0.5) / n - 0.5, ...).
  cv::Mat ray_map(int supersample = 1) const;

 private:
  int width_ = 0;
  int height_ = 0;
  LensModel model_ = LensModel::kOpenCV5;
  std::vector<double> params_;
};

// Reads an OpenCV calibration YAML/JSON file (camera_matrix, distortion_coefficients,
// image_width, image_height). Throws Error(kIo / kInvalidArgument) naming the file and field.
CameraModel read_camera_model(const std::string& path);

// Extra fields written along with the model.
struct CalibrationFileExtras {
  int nr_of_frames = -1;               // omitted if < 0
  double avg_reprojection_error = -1;  // omitted if < 0
  std::vector<double> param_std;       // per-parameter standard deviations (omitted if empty)
  std::vector<std::pair<std::string, std::string>> strings;  // free-form text fields
};
// Writes OpenCV YAML (".yml"/".yaml") or JSON (".json") in cv::FileStorage format.
void write_camera_model(const std::string& path, const CameraModel& model,
                        const CalibrationFileExtras& extras = {});

// The Logitech C525 calibration of the paper's experiments (1280x720), built in so the
// project reads no file outside its own tree at run time (data/c525_reference.yml is the same).
CameraModel c525_reference_model();

}  // namespace posecal
