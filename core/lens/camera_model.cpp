#include "lens/camera_model.hpp"

#include <ceres/jet.h>

#include "common/error.hpp"

namespace posecal {

CameraModel::CameraModel(int width, int height, LensModel model, std::vector<double> params)
    : width_(width), height_(height), model_(model), params_(std::move(params)) {
  if (static_cast<int>(params_.size()) != num_intrinsics(model_)) {
    throw Error(ErrorCode::kInvalidArgument,
                std::string("camera model '") + lens_model_name(model_) + "' needs " +
                    std::to_string(num_intrinsics(model_)) + " parameters, got " +
                    std::to_string(params_.size()));
  }
}

CameraModel CameraModel::pinhole(LensModel model, int width, int height, double fx, double fy, double cx, double cy) {
  std::vector<double> params(num_intrinsics(model), 0.0);
  params[0] = fx, params[1] = fy, params[2] = cx, params[3] = cy;
  return CameraModel(width, height, model, std::move(params));
}

CameraModel CameraModel::opencv5(int width, int height, double fx, double fy, double cx, double cy,
                                 const std::array<double, 5>& d) {
  return CameraModel(width, height, LensModel::kOpenCV5,
                     {fx, fy, cx, cy, d[0], d[1], d[2], d[3], d[4]});
}

cv::Matx33d CameraModel::camera_matrix() const { return {fx(), 0, cx(), 0, fy(), cy(), 0, 0, 1}; }

std::vector<double> CameraModel::distortion_coefficients() const {
  return {params_.begin() + kNumPinholeParams, params_.end()};
}

CameraModel CameraModel::from_opencv(int width, int height, const cv::Matx33d& K,
                                     const std::vector<double>& dist) {
  if (dist.size() != 4 && dist.size() != 5 && dist.size() != 8 && dist.size() != 12 &&
      dist.size() != 14) {
    throw Error(ErrorCode::kInvalidArgument,
                "distortion_coefficients must have 4, 5, 8, 12 or 14 entries, got " +
                    std::to_string(dist.size()));
  }
  // The count says the model (4 coefficients: opencv5 with k3 = 0), as OpenCV's own functions
  // read the vector.
  const int count = static_cast<int>(dist.size());
  const std::optional<LensModel> model = lens_model_of_opencv_count(count == 4 ? 5 : count);
  if (!model) {
    throw Error(ErrorCode::kUnsupported, "no lens model holds an OpenCV distortion vector of " +
                                             std::to_string(count) + " coefficients");
  }
  const int model_count = num_distortion_params(*model);
  if (K(0, 1) != 0.0) {
    throw Error(ErrorCode::kUnsupported, "camera_matrix has skew; the model has no skew term");
  }
  std::vector<double> params{K(0, 0), K(1, 1), K(0, 2), K(1, 2)};
  for (int i = 0; i < model_count; ++i) params.push_back(i < static_cast<int>(dist.size()) ? dist[i] : 0.0);
  return CameraModel(width, height, *model, std::move(params));
}

CameraModel CameraModel::from_opencv_fisheye(int width, int height, const cv::Matx33d& K,
                                             const std::vector<double>& dist) {
  if (dist.size() != 4) {
    throw Error(ErrorCode::kInvalidArgument,
                "a fisheye model has 4 distortion coefficients (k1..k4), got " +
                    std::to_string(dist.size()));
  }
  if (K(0, 1) != 0.0) {
    throw Error(ErrorCode::kUnsupported, "camera_matrix has skew; the model has no skew term");
  }
  return CameraModel(width, height, LensModel::kFisheye,
                     {K(0, 0), K(1, 1), K(0, 2), K(1, 2), dist[0], dist[1], dist[2], dist[3]});
}

bool CameraModel::is_valid(std::string* why) const {
  auto fail = [&](const std::string& msg) {
    if (why) *why = msg;
    return false;
  };
  if (width_ <= 0 || height_ <= 0) return fail("image size must be positive");
  if (width_ > kMaxImageSide || height_ > kMaxImageSide ||
      static_cast<long long>(width_) * height_ > kMaxImagePixels) {
    return fail("image size " + std::to_string(width_) + "x" + std::to_string(height_) +
                " is beyond the limit of " + std::to_string(kMaxImageSide) +
                " pixels per side and " + std::to_string(kMaxImagePixels) + " pixels");
  }
  if (static_cast<int>(params_.size()) != num_intrinsics(model_))
    return fail("wrong parameter count");
  for (size_t i = 0; i < params_.size(); ++i) {
    if (!std::isfinite(params_[i])) return fail("parameter " + param_names()[i] + " is not finite");
  }
  if (fx() <= 0 || fy() <= 0) return fail("focal lengths must be positive");
  return true;
}

Eigen::Vector2d CameraModel::distort(const Eigen::Vector2d& xn) const {
  Eigen::Vector2d out;
  distort_generic(model_, params_.data() + kNumPinholeParams, xn.x(), xn.y(), &out.x(), &out.y());
  return out;
}

namespace {

// True if the model projects the direction p_cam (see CameraModel::project).
bool in_field(const CameraModel& m, const Eigen::Vector3d& p_cam) {
  return with_lens_model(m.lens_model(), [&](auto lm) {
    using M = decltype(lm);
    if constexpr (M::kRayModel) {
      if (!p_cam.allFinite() || p_cam.isZero()) return false;
      const double theta = std::atan2(p_cam.head<2>().norm(), p_cam.z());
      return theta < M_PI && M::max_theta(m.params().data() + kNumPinholeParams, theta) >= theta;
    } else {
      return p_cam.z() > 0;
    }
  });
}

}  // namespace

double CameraModel::max_ray_angle() const {
  return with_lens_model(model_, [&](auto lm) {
    using M = decltype(lm);
    if constexpr (M::kRayModel) return M::max_theta(params_.data() + kNumPinholeParams);
    return 0.5 * M_PI * (1 - 1e-9);
  });
}

bool CameraModel::project(const Eigen::Vector3d& p_cam, Eigen::Vector2d* uv) const {
  if (!in_field(*this, p_cam)) return false;
  project_generic(model_, params_.data(), p_cam.data(), uv->data());
  return true;
}

bool CameraModel::project(const Eigen::Vector3d& p_cam, Eigen::Vector2d* uv,
                          Eigen::Matrix<double, 2, 3>* J_p,
                          Eigen::Matrix<double, 2, Eigen::Dynamic>* J_params) const {
  if (!in_field(*this, p_cam)) return false;
  // Automatic differentiation through the same templated projection used by the solver.
  constexpr int kN = 3 + kMaxIntrinsics;
  using Jet = ceres::Jet<double, kN>;
  const int n = num_params();
  Jet jp[3], jparams[kMaxIntrinsics], juv[2];
  for (int i = 0; i < 3; ++i) jp[i] = Jet(p_cam[i], i);
  for (int i = 0; i < n; ++i) jparams[i] = Jet(params_[i], 3 + i);
  project_generic(model_, jparams, jp, juv);
  (*uv) << juv[0].a, juv[1].a;
  if (J_p) {
    for (int r = 0; r < 2; ++r)
      for (int c = 0; c < 3; ++c) (*J_p)(r, c) = juv[r].v[c];
  }
  if (J_params) {
    J_params->resize(2, n);
    for (int r = 0; r < 2; ++r)
      for (int c = 0; c < n; ++c) (*J_params)(r, c) = juv[r].v[3 + c];
  }
  return true;
}

}  // namespace posecal
