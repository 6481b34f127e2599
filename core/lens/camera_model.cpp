#include "lens/camera_model.hpp"

#include <ceres/jet.h>

#include <Eigen/Dense>
#include <ctime>
#include <fstream>
#include <limits>
#include <opencv2/core/persistence.hpp>

#include "common/error.hpp"

namespace posecal {

const char* error_code_name(ErrorCode code) {
  switch (code) {
    case ErrorCode::kInvalidArgument:
      return "invalid argument";
    case ErrorCode::kNotFound:
      return "not found";
    case ErrorCode::kBufferTooSmall:
      return "buffer too small";
    case ErrorCode::kTimeout:
      return "timeout";
    case ErrorCode::kDevice:
      return "device error";
    case ErrorCode::kState:
      return "wrong state";
    case ErrorCode::kIo:
      return "I/O error";
    case ErrorCode::kInternal:
      return "internal error";
    case ErrorCode::kDegenerate:
      return "degenerate data";
    case ErrorCode::kUnsupported:
      return "unsupported";
  }
  return "unknown error";
}

namespace {

struct LensModelInfo {
  const char* name;
  std::vector<std::string> names;  // all intrinsics, pinhole first
};

const LensModelInfo& info(LensModel model) {
  static const LensModelInfo opencv5{"opencv5",
                                     {"fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3"}};
  switch (model) {
    case LensModel::kOpenCV5:
      return opencv5;
  }
  throw Error(ErrorCode::kInternal, "unknown lens model");
}

// Distortion of a normalised point and its 2x2 Jacobian d(xd, yd)/d(x, y).
[[gnu::always_inline]] inline void distort_with_jacobian(LensModel model, const double* dist, double x, double y, double* xd,
                           double* yd, Eigen::Matrix2d* J) {
  if (model == LensModel::kOpenCV5) {
    const double k1 = dist[0], k2 = dist[1], p1 = dist[2], p2 = dist[3], k3 = dist[4];
    const double x2 = x * x, y2 = y * y, xy = x * y, r2 = x2 + y2;
    const double radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3));
    const double dradial_dr2 = k1 + r2 * (2 * k2 + 3 * k3 * r2);
    *xd = x * radial + 2 * p1 * xy + p2 * (r2 + 2 * x2);
    *yd = y * radial + p1 * (r2 + 2 * y2) + 2 * p2 * xy;
    (*J)(0, 0) = radial + 2 * x2 * dradial_dr2 + 2 * p1 * y + 6 * p2 * x;
    (*J)(0, 1) = 2 * xy * dradial_dr2 + 2 * p1 * x + 2 * p2 * y;
    (*J)(1, 0) = 2 * xy * dradial_dr2 + 2 * p1 * x + 2 * p2 * y;
    (*J)(1, 1) = radial + 2 * y2 * dradial_dr2 + 6 * p1 * y + 2 * p2 * x;
    return;
  }
  // Generic path for models without a hand-written Jacobian.
  using Jet = ceres::Jet<double, 2>;
  Jet jx(x, 0), jy(y, 1), jxd, jyd;
  Jet jdist[kMaxIntrinsics];
  for (int i = 0; i < num_distortion_params(model); ++i) jdist[i] = Jet(dist[i]);
  distort_generic(model, jdist, jx, jy, &jxd, &jyd);
  *xd = jxd.a;
  *yd = jyd.a;
  J->row(0) = jxd.v.transpose();
  J->row(1) = jyd.v.transpose();
}

}  // namespace

int num_distortion_params(LensModel model) {
  return static_cast<int>(info(model).names.size()) - kNumPinholeParams;
}
const std::vector<std::string>& intrinsic_names(LensModel model) { return info(model).names; }
const char* lens_model_name(LensModel model) { return info(model).name; }

CameraModel::CameraModel(int width, int height, LensModel model, std::vector<double> params)
    : width_(width), height_(height), model_(model), params_(std::move(params)) {
  if (static_cast<int>(params_.size()) != num_intrinsics(model_)) {
    throw Error(ErrorCode::kInvalidArgument,
                std::string("camera model '") + lens_model_name(model_) + "' needs " +
                    std::to_string(num_intrinsics(model_)) + " parameters, got " +
                    std::to_string(params_.size()));
  }
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
  std::array<double, 5> d{0, 0, 0, 0, 0};
  if (dist.size() != 4 && dist.size() != 5 && dist.size() != 8 && dist.size() != 12 &&
      dist.size() != 14) {
    throw Error(ErrorCode::kInvalidArgument,
                "distortion_coefficients must have 4, 5, 8, 12 or 14 entries, got " +
                    std::to_string(dist.size()));
  }
  for (size_t i = 0; i < dist.size(); ++i) {
    if (i < 5) {
      d[i] = dist[i];
    } else if (dist[i] != 0.0) {
      throw Error(ErrorCode::kUnsupported,
                  "distortion coefficient " + std::to_string(i) +
                      " is non-zero: rational/thin-prism/tilt models are not supported yet");
    }
  }
  if (K(0, 1) != 0.0) {
    throw Error(ErrorCode::kUnsupported, "camera_matrix has skew; the model has no skew term");
  }
  return opencv5(width, height, K(0, 0), K(1, 1), K(0, 2), K(1, 2), d);
}

bool CameraModel::is_valid(std::string* why) const {
  auto fail = [&](const std::string& msg) {
    if (why) *why = msg;
    return false;
  };
  if (width_ <= 0 || height_ <= 0) return fail("image size must be positive");
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

bool CameraModel::project(const Eigen::Vector3d& p_cam, Eigen::Vector2d* uv) const {
  if (!(p_cam.z() > 0)) return false;
  project_generic(model_, params_.data(), p_cam.data(), uv->data());
  return true;
}

bool CameraModel::project(const Eigen::Vector3d& p_cam, Eigen::Vector2d* uv,
                          Eigen::Matrix<double, 2, 3>* J_p,
                          Eigen::Matrix<double, 2, Eigen::Dynamic>* J_params) const {
  if (!(p_cam.z() > 0)) return false;
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

namespace {

// A radius (normalised coordinates) inside which the distortion's Jacobian is positive
// definite, so it cannot fold: 0 if none is known. For the OpenCV model J = A + T with
// A = radial I + 2 radial' v v^T (v = (x, y), radial' = d radial / d r^2; eigenvalues radial and
// radial + 2 r^2 radial') and the symmetric tangential part T, |T| <= c r (Frobenius norm), so by
// Weyl's inequality J > 0 wherever min(radial, radial + 2 r^2 radial') > c r. That holds on
// [0, r] for the r found by stepping out with a Lipschitz bound on both polynomials.
double fold_free_radius_of(LensModel model, const double* dist) {
  if (model != LensModel::kOpenCV5) return 0.0;
  const double k1 = dist[0], k2 = dist[1], p1 = std::abs(dist[2]), p2 = std::abs(dist[3]), k3 = dist[4];
  const double t11 = 2 * p1 + 6 * p2, t12 = 2 * p1 + 2 * p2, t22 = 6 * p1 + 2 * p2;
  const double c = std::sqrt(t11 * t11 + 2 * t12 * t12 + t22 * t22);
  auto lower = [&](double r) {  // min of the two eigenvalue bounds at r
    const double r2 = r * r, r4 = r2 * r2, r6 = r4 * r2;
    return std::min(1 + k1 * r2 + k2 * r4 + k3 * r6, 1 + 3 * k1 * r2 + 5 * k2 * r4 + 7 * k3 * r6) - c * r;
  };
  auto lipschitz = [&](double r) {  // bound on |d lower / dr| over [0, r]
    const double r3 = r * r * r, r5 = r3 * r * r;
    return 6 * std::abs(k1) * r + 20 * std::abs(k2) * r3 + 42 * std::abs(k3) * r5 + c;
  };
  // Adaptive steps: lower > 0 on [r, r + h] if h < lower(r) / L, L bounding the slope there.
  constexpr double kMaxStep = 0.05, kMinStep = 1e-4, kMax = 4.0;
  double r = 0;
  while (r < kMax) {
    const double h = std::min(kMaxStep, 0.5 * lower(r) / lipschitz(r + kMaxStep));
    if (!(h >= kMinStep)) break;
    r += h;
  }
  return std::min(r, kMax);
}

// Solves distort(x) = target by damped Newton from `x`. Rejects solutions where the
// distortion folds over (det J <= 0): there the model has no physical preimage. Inside
// `fold_free_r` (fold_free_radius_of()) the check along the ray is known to pass and is skipped.
bool invert_distortion(LensModel model, const double* dist, double tx, double ty, double* x,
                       double* y, double fold_free_r = 0.0) {
  double cx = *x, cy = *y;
  Eigen::Matrix2d J;
  double xd, yd;
  distort_with_jacobian(model, dist, cx, cy, &xd, &yd, &J);
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
      distort_with_jacobian(model, dist, nx, ny, &nxd, &nyd, &nJ);
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
      distort_with_jacobian(model, dist, f * cx, f * cy, &ux, &uy, &Jf);
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
  return fold_free_radius_of(model_, params_.data() + kNumPinholeParams);
}

bool CameraModel::unproject(const Eigen::Vector2d& uv, Eigen::Vector2d* xn, double fold_free_r) const {
  const double tx = (uv.x() - cx()) / fx();
  const double ty = (uv.y() - cy()) / fy();
  double x = tx, y = ty;
  if (!invert_distortion(model_, params_.data() + kNumPinholeParams, tx, ty, &x, &y, fold_free_r)) return false;
  *xn << x, y;
  return true;
}

cv::Mat CameraModel::ray_map(int supersample) const {
  if (supersample < 1) throw Error(ErrorCode::kInvalidArgument, "supersample must be >= 1");
  const int W = width_ * supersample, H = height_ * supersample;
  cv::Mat map(H, W, CV_32FC2);
  const double* dist = params_.data() + kNumPinholeParams;
  const float nan = std::numeric_limits<float>::quiet_NaN();
  const double fold_free_r = fold_free_radius_of(model_, dist);
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
      bool ok = invert_distortion(model_, dist, tx, ty, &sx, &sy, fold_free_r);
      if (!ok && have_prev) {
        sx = tx;
        sy = ty;
        ok = invert_distortion(model_, dist, tx, ty, &sx, &sy, fold_free_r);
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
  return map;
}

cv::Mat CameraModel::distortion_map(int step) const {
  if (step < 1) throw Error(ErrorCode::kInvalidArgument, "distortion map step must be >= 1");
  const int rows = (height_ + step - 1) / step, cols = (width_ + step - 1) / step;
  cv::Mat map(rows, cols, CV_32F);
  const double* dist = params_.data() + kNumPinholeParams;
  const double fold_free_r = fold_free_radius_of(model_, dist);
  // Row start of the previous row, for the next row's warm start.
  bool have_above = false;
  double ax = 0, ay = 0;
  for (int i = 0; i < rows; ++i) {
    const double ty = (i * step - cy()) / fy();
    // Warm start (the map is smooth): the left neighbours' solutions extrapolated linearly, or the
    // one left neighbour, or for the first cell the row above's; Newton then needs one or two
    // steps.
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
      bool ok = invert_distortion(model_, dist, tx, ty, &x, &y, fold_free_r);
      if (!ok && (x != tx || y != ty)) {  // warm-started: retry from the pinhole ray
        x = tx;
        y = ty;
        ok = invert_distortion(model_, dist, tx, ty, &x, &y, fold_free_r);
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
  return map;
}

CameraModel read_camera_model(const std::string& path) {
  // Checked here so OpenCV does not log its own error into the host's stderr.
  if (!std::ifstream(path).good()) throw Error(ErrorCode::kIo, "cannot open camera model file '" + path + "'");
  cv::FileStorage fs;
  try {
    if (!fs.open(path, cv::FileStorage::READ)) {
      throw Error(ErrorCode::kIo, "cannot open camera model file '" + path + "'");
    }
  } catch (const cv::Exception& e) {
    throw Error(ErrorCode::kInvalidArgument,
                "camera model file '" + path + "' is not valid OpenCV YAML/JSON: " + e.msg);
  }
  auto need = [&](const char* key) {
    cv::FileNode n = fs[key];
    if (n.empty() || n.isNone()) {
      throw Error(ErrorCode::kInvalidArgument,
                  "camera model file '" + path + "' has no field '" + key + "'");
    }
    return n;
  };
  try {
    cv::Mat K, D;
    need("camera_matrix") >> K;
    need("distortion_coefficients") >> D;
    const cv::FileNode wn = need("image_width"), hn = need("image_height");
    if (!wn.isReal() && !wn.isInt()) {
      throw Error(ErrorCode::kInvalidArgument, "'" + path + "': image_width is not a number");
    }
    if (!hn.isReal() && !hn.isInt()) {
      throw Error(ErrorCode::kInvalidArgument, "'" + path + "': image_height is not a number");
    }
    const double w = static_cast<double>(wn), h = static_cast<double>(hn);
    if (K.rows != 3 || K.cols != 3) {
      throw Error(ErrorCode::kInvalidArgument, "'" + path + "': camera_matrix is not 3x3");
    }
    if (D.total() == 0 || (D.rows != 1 && D.cols != 1)) {
      throw Error(ErrorCode::kInvalidArgument,
                  "'" + path + "': distortion_coefficients is not a vector");
    }
    if (!(w > 0 && h > 0 && w < 1e6 && h < 1e6 && w == std::floor(w) && h == std::floor(h))) {
      throw Error(ErrorCode::kInvalidArgument,
                  "'" + path + "': image_width/image_height must be positive integers");
    }
    K.convertTo(K, CV_64F);
    D.convertTo(D, CV_64F);
    std::vector<double> d(D.begin<double>(), D.end<double>());
    CameraModel model = CameraModel::from_opencv(static_cast<int>(w), static_cast<int>(h),
                                                 cv::Matx33d(K.ptr<double>()), d);
    std::string why;
    if (!model.is_valid(&why)) {
      throw Error(ErrorCode::kInvalidArgument, "'" + path + "': " + why);
    }
    return model;
  } catch (const cv::Exception& e) {
    throw Error(ErrorCode::kInvalidArgument, "camera model file '" + path + "': " + e.msg);
  }
}

void write_camera_model(const std::string& path, const CameraModel& model,
                        const CalibrationFileExtras& extras) {
  cv::FileStorage fs;
  try {
    if (!fs.open(path, cv::FileStorage::WRITE)) {
      throw Error(ErrorCode::kIo, "cannot write calibration file '" + path + "'");
    }
  } catch (const cv::Exception& e) {
    throw Error(ErrorCode::kIo, "cannot write calibration file '" + path + "': " + e.msg);
  }
  char stamp[64];
  const std::time_t now = std::time(nullptr);
  std::tm tm_utc{};
  gmtime_r(&now, &tm_utc);
  std::strftime(stamp, sizeof stamp, "%Y-%m-%dT%H:%M:%SZ", &tm_utc);
  fs << "calibration_time" << std::string(stamp);
  if (extras.nr_of_frames >= 0) fs << "nr_of_frames" << extras.nr_of_frames;
  fs << "image_width" << model.width();
  fs << "image_height" << model.height();
  fs << "lens_model" << std::string(lens_model_name(model.lens_model()));
  fs << "camera_matrix" << cv::Mat(model.camera_matrix());
  const std::vector<double> d = model.distortion_coefficients();
  fs << "distortion_coefficients"
     << cv::Mat(1, static_cast<int>(d.size()), CV_64F, const_cast<double*>(d.data()));
  if (extras.avg_reprojection_error >= 0) {
    fs << "avg_reprojection_error" << extras.avg_reprojection_error;
  }
  if (!extras.param_std.empty()) {
    std::string names;
    for (const auto& n : model.param_names()) names += (names.empty() ? "" : " ") + n;
    fs << "intrinsic_names" << names;
    fs << "std_deviations_intrinsics"
       << cv::Mat(1, static_cast<int>(extras.param_std.size()), CV_64F,
                  const_cast<double*>(extras.param_std.data()));
  }
  for (const auto& [key, value] : extras.strings) fs << key << value;
  fs.release();
}

CameraModel c525_reference_model() {
  // data/c525_reference.yml: real Logitech C525 calibration, 1280x720, 9 frames.
  return CameraModel::opencv5(
      1280, 720, 1.0687250840763766e+03, 1.0737431805568067e+03, 6.3526070691971165e+02,
      3.5555335970090516e+02,
      {-3.1759579767319194e-03, -2.0593634553884241e-01, -2.8115339213691912e-03,
       -3.8662066741185558e-03, 2.4780625930115230e-01});
}

}  // namespace posecal
