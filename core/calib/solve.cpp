// Calibration: Zhang's initial solution (OpenCV) refined by a Ceres bundle adjustment over the
// intrinsics and every frame's board pose (paper eq. 3); the covariance is covariance.cpp's.
#include <ceres/ceres.h>
#include <ceres/rotation.h>
#include <glog/logging.h>

#include <Eigen/Dense>
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdlib>
#include <limits>
#include <mutex>
#include <opencv2/calib3d.hpp>

#include "calib/calibration.hpp"
#include "calib/information.hpp"
#include "calib/pose_estimation.hpp"
#include "calib/solve_internal.hpp"
#include "common/error.hpp"

namespace posecal {

const char* solver_termination_name(SolverTermination t) {
  switch (t) {
    case SolverTermination::kConvergence: return "convergence";
    case SolverTermination::kNoConvergence: return "no_convergence";
  }
  return "unknown";
}

bool CalibrationOptions::is_valid(std::string* error) const {
  auto fail = [&](const std::string& why) {
    if (error) *error = why;
    return false;
  };
  if (max_iterations < 1 || max_iterations > 10000)
    return fail("max_iterations must be in [1, 10000]");
  if (!(function_tolerance > 0) || !(parameter_tolerance > 0))
    return fail("tolerances must be > 0");
  if (!(max_relative_focal_std > 0)) return fail("max_relative_focal_std must be > 0");
  const auto& names = intrinsic_names(lens_model);
  for (const auto& f : fixed) {
    if (std::find(names.begin(), names.end(), f) == names.end()) {
      return fail("unknown parameter '" + f + "' in fixed list");
    }
  }
  for (const auto& h : hold_if_undetermined) {
    if (std::find(names.begin(), names.end(), h) == names.end()) {
      return fail("unknown parameter '" + h + "' in the list of those held when undetermined");
    }
  }
  if (prior) {
    const IntrinsicsPrior& p = *prior;
    const int m = static_cast<int>(p.names.size());
    if (static_cast<int>(p.mean.size()) != num_intrinsics(lens_model))
      return fail("prior: the mean has " + std::to_string(p.mean.size()) +
                  " values, the lens model " + std::to_string(num_intrinsics(lens_model)));
    if (m == 0) return fail("prior: no parameter");
    for (const auto& n : p.names)
      if (std::find(names.begin(), names.end(), n) == names.end())
        return fail("prior: unknown parameter '" + n + "'");
    if (p.covariance.rows() != m || p.covariance.cols() != m)
      return fail("prior: the covariance is not " + std::to_string(m) + "x" + std::to_string(m));
    for (double v : p.mean)
      if (!std::isfinite(v)) return fail("prior: the mean is not finite");
    if (!p.covariance.allFinite()) return fail("prior: the covariance is not finite");
    if (!(p.noise_px > 0 && std::isfinite(p.noise_px))) return fail("prior: noise_px must be > 0");
  }
  return true;
}

namespace {

// Reprojection residual of one board point (paper eq. 3): pi(P; R, t, C) - p, lens model M.
template <class M>
struct ReprojectionCost {
  static constexpr int N = kNumParamsOf<M>;
  double u, v;
  double X, Y, Z;
  double aspect;  // > 0: fy is fx * aspect (fixed aspect ratio)

  template <typename T>
  bool operator()(const T* intrinsics, const T* rt, T* residual) const {
    const T P[3] = {T(X), T(Y), T(Z)};
    T pc[3];
    ceres::AngleAxisRotatePoint(rt, P, pc);
    pc[0] += rt[3];
    pc[1] += rt[4];
    pc[2] += rt[5];
    if constexpr (M::kRayModel) {
      // A ray model sees beyond 90 degrees; only the camera's centre and the ray straight behind
      // it have no projection.
      if (!(pc[0] * pc[0] + pc[1] * pc[1] > T(1e-18) * pc[2] * pc[2] || pc[2] > T(1e-9)))
        return false;
    } else {
      if (!(pc[2] > T(1e-9))) return false;  // behind the camera: reject the step
    }
    T params[N];
    for (int i = 0; i < N; ++i) params[i] = intrinsics[i];
    if (aspect > 0) params[1] = params[0] * T(aspect);
    T uv[2];
    project_with<M>(params, pc, uv);
    residual[0] = uv[0] - T(u);
    residual[1] = uv[1] - T(v);
    return true;
  }
};

ceres::CostFunction* make_cost(LensModel model, const cv::Point2d& p, const cv::Point3d& P,
                               double aspect) {
  return with_lens_model(model, [&](auto m) -> ceres::CostFunction* {
    using Cost = ReprojectionCost<decltype(m)>;
    return new ceres::AutoDiffCostFunction<Cost, 2, Cost::N, 6>(new Cost{p.x, p.y, P.x, P.y, P.z, aspect});
  });
}

// The prior's term (IntrinsicsPrior): r = noise_px * U (x_S - mean_S), where U^T U is the inverse
// of the prior covariance over the parameters S it names, so that |r|^2 is noise_px^2 times the
// squared Mahalanobis distance. Linear in the intrinsics: the Jacobian is constant.
class PriorCost final : public ceres::CostFunction {
 public:
  PriorCost(const IntrinsicsPrior& prior, const std::vector<std::string>& names) {
    const int m = static_cast<int>(prior.names.size());
    const int n = static_cast<int>(names.size());
    const Eigen::MatrixXd information = prior.covariance.inverse();
    Eigen::LLT<Eigen::MatrixXd> llt(information);
    if (llt.info() != Eigen::Success || !information.allFinite()) {
      throw Error(ErrorCode::kInvalidArgument,
                  "calibration: the prior's covariance is not positive definite");
    }
    const Eigen::MatrixXd U = prior.noise_px * Eigen::MatrixXd(llt.matrixU());
    jacobian_ = Eigen::MatrixXd::Zero(m, n);
    offset_ = Eigen::VectorXd::Zero(m);
    Eigen::VectorXd mean_s(m);
    for (int a = 0; a < m; ++a) {
      const int i =
          static_cast<int>(std::find(names.begin(), names.end(), prior.names[a]) - names.begin());
      jacobian_.col(i) = U.col(a);
      mean_s[a] = prior.mean[i];
    }
    offset_ = -U * mean_s;
    set_num_residuals(m);
    mutable_parameter_block_sizes()->push_back(n);
  }
  bool Evaluate(double const* const* parameters, double* residuals,
                double** jacobians) const override {
    const Eigen::Map<const Eigen::VectorXd> x(parameters[0], jacobian_.cols());
    Eigen::Map<Eigen::VectorXd>(residuals, jacobian_.rows()) = jacobian_ * x + offset_;
    if (jacobians != nullptr && jacobians[0] != nullptr) {
      // Ceres' Jacobians are row-major.
      Eigen::Map<Eigen::Matrix<double, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor>>(
          jacobians[0], jacobian_.rows(), jacobian_.cols()) = jacobian_;
    }
    return true;
  }

 private:
  Eigen::MatrixXd jacobian_;
  Eigen::VectorXd offset_;
};

// The prior's rows that constrain a free parameter (each adds one pseudo-observation).
int prior_rows(const CalibrationOptions& options, const std::vector<bool>& fixed) {
  if (!options.prior) return 0;
  const auto& names = intrinsic_names(options.lens_model);
  int rows = 0;
  for (const auto& n : options.prior->names) {
    const auto i = std::find(names.begin(), names.end(), n) - names.begin();
    if (!fixed[i]) ++rows;
  }
  return rows;
}

void check_prior_size(const CalibrationOptions& options, cv::Size image_size) {
  if (!options.prior || options.prior->image_size.empty() ||
      options.prior->image_size == image_size)
    return;
  const cv::Size p = options.prior->image_size;
  throw Error(ErrorCode::kInvalidArgument,
              "calibration: the prior is for " + std::to_string(p.width) + "x" +
                  std::to_string(p.height) + " images, these are " +
                  std::to_string(image_size.width) + "x" + std::to_string(image_size.height));
}

void check_frames(const std::vector<Observation>& frames) {
  if (frames.empty()) throw Error(ErrorCode::kInvalidArgument, "calibration: no frames");
  for (size_t f = 0; f < frames.size(); ++f) {
    const Observation& o = frames[f];
    if (o.image_points.size() != o.board_points.size()) {
      throw Error(ErrorCode::kInvalidArgument,
                  "calibration: frame " + std::to_string(f) + " has " +
                      std::to_string(o.image_points.size()) + " image points but " +
                      std::to_string(o.board_points.size()) + " board points");
    }
    if (o.size() < 4) {
      throw Error(ErrorCode::kDegenerate, "calibration: frame " + std::to_string(f) + " has only " +
                                              std::to_string(o.size()) +
                                              " points; a pose needs at least 4");
    }
    for (size_t i = 0; i < o.size(); ++i) {
      const auto& p = o.image_points[i];
      const auto& P = o.board_points[i];
      if (!std::isfinite(p.x) || !std::isfinite(p.y) || !std::isfinite(P.x) ||
          !std::isfinite(P.y) || !std::isfinite(P.z)) {
        throw Error(ErrorCode::kInvalidArgument, "calibration: frame " + std::to_string(f) +
                                                     " has a non-finite point (index " +
                                                     std::to_string(i) + ")");
      }
    }
  }
}

// Zhang's method as OpenCV implements it, pinhole only (distortion held at zero): a stable start
// for the full bundle adjustment, which then frees the distortion.
bool zhang_initial(const std::vector<Observation>& frames, cv::Size size, LensModel lens, bool fix_pp,
                   bool fix_aspect, CameraModel* model, std::vector<Pose>* poses) {
  std::vector<std::vector<cv::Point3f>> obj;
  std::vector<std::vector<cv::Point2f>> img;
  for (const auto& f : frames) {
    obj.emplace_back(f.board_points.begin(), f.board_points.end());
    img.emplace_back(f.image_points.begin(), f.image_points.end());
  }
  int flags = cv::CALIB_FIX_K1 | cv::CALIB_FIX_K2 | cv::CALIB_FIX_K3 | cv::CALIB_ZERO_TANGENT_DIST;
  if (fix_pp) flags |= cv::CALIB_FIX_PRINCIPAL_POINT;
  if (fix_aspect) flags |= cv::CALIB_FIX_ASPECT_RATIO;
  cv::Mat K = (cv::Mat_<double>(3, 3) << 1, 0, (size.width - 1) * 0.5, 0, 1,
               (size.height - 1) * 0.5, 0, 0, 1);
  cv::Mat D = cv::Mat::zeros(1, 5, CV_64F);
  std::vector<cv::Mat> rvecs, tvecs;
  try {
    if (fix_pp || fix_aspect) {
      // OpenCV needs a starting K for these flags; take its closed-form guess (pp at centre).
      cv::Mat K0 = cv::initCameraMatrix2D(obj, img, size, 1.0);
      if (!cv::checkRange(K0) || K0.at<double>(0, 0) <= 0) return false;
      K.at<double>(0, 0) = K0.at<double>(0, 0);
      K.at<double>(1, 1) = fix_aspect ? K0.at<double>(0, 0) : K0.at<double>(1, 1);
      flags |= cv::CALIB_USE_INTRINSIC_GUESS;
    }
    cv::calibrateCamera(
        obj, img, size, K, D, rvecs, tvecs, flags,
        cv::TermCriteria(cv::TermCriteria::COUNT + cv::TermCriteria::EPS, 30, 1e-9));
  } catch (const cv::Exception&) {
    return false;
  }
  if (!cv::checkRange(K) || K.at<double>(0, 0) <= 0 || K.at<double>(1, 1) <= 0) return false;
  *model = CameraModel::pinhole(lens, size.width, size.height, K.at<double>(0, 0), K.at<double>(1, 1),
                                K.at<double>(0, 2), K.at<double>(1, 2));
  poses->clear();
  for (size_t i = 0; i < rvecs.size(); ++i) {
    Pose p;
    p.r << rvecs[i].at<double>(0), rvecs[i].at<double>(1), rvecs[i].at<double>(2);
    p.t << tvecs[i].at<double>(0), tvecs[i].at<double>(1), tvecs[i].at<double>(2);
    if (!p.is_finite()) return false;
    poses->push_back(p);
  }
  return true;
}

// Mean squared pixel error of every frame's board under the equidistant projection (theta_d =
// theta) with focal length f and principal point c, each pose from its rays by the linear fit
// (pose_from_rays without refinement); infinity if a frame's pose is not determined. `poses`
// (optional) receives the poses, refined.
double equidistant_fit(const std::vector<Observation>& frames, double f, const Eigen::Vector2d& c,
                       std::vector<Pose>* poses) {
  double sum = 0;
  size_t count = 0;
  std::vector<cv::Point3d> object;
  std::vector<Eigen::Vector3d> rays;
  if (poses) poses->clear();
  for (const Observation& o : frames) {
    object.clear();
    rays.clear();
    for (size_t i = 0; i < o.size(); ++i) {
      const Eigen::Vector2d d = (Eigen::Vector2d(o.image_points[i].x, o.image_points[i].y) - c) / f;
      const double theta = d.norm();
      if (!(theta < M_PI)) continue;  // beyond the field of any lens with this f
      const double s = theta > 1e-12 ? std::sin(theta) / theta : 1.0;
      rays.emplace_back(s * d.x(), s * d.y(), std::cos(theta));
      object.push_back(o.board_points[i]);
    }
    Pose pose;
    if (!pose_from_rays(object, rays, &pose, poses != nullptr))
      return std::numeric_limits<double>::infinity();
    if (poses) poses->push_back(pose);
    const Eigen::Matrix3d R = pose.R();
    for (size_t i = 0; i < o.size(); ++i) {
      const cv::Point3d& P = o.board_points[i];
      const Eigen::Vector3d pc = R * Eigen::Vector3d(P.x, P.y, P.z) + pose.t;
      const double rho = pc.head<2>().norm();
      const double theta = std::atan2(rho, pc.z());
      const Eigen::Vector2d uv = c + (rho > 0 ? f * theta / rho : 0.0) * pc.head<2>();
      sum += (uv - Eigen::Vector2d(o.image_points[i].x, o.image_points[i].y)).squaredNorm();
      ++count;
    }
  }
  return count > 0 ? sum / static_cast<double>(count) : std::numeric_limits<double>::infinity();
}

// A ray model's start (the fisheye; Zhang's pinhole start cannot hold rays beyond 90 degrees and
// is poor long before): the equidistant projection, distortion 0, principal point at the image
// centre, and the focal length that best explains every frame (equidistant_fit): a grid from
// 0.05 to 5 image widths, then golden-section search on log f about the best grid point; the
// poses refined at that f.
bool equidistant_initial(const std::vector<Observation>& frames, cv::Size size, LensModel lens,
                         CameraModel* model, std::vector<Pose>* poses) {
  const Eigen::Vector2d c((size.width - 1) * 0.5, (size.height - 1) * 0.5);
  const double lo = std::log(0.05 * size.width), hi = std::log(5.0 * size.width);
  constexpr int kGrid = 60;
  auto cost = [&](double log_f) { return equidistant_fit(frames, std::exp(log_f), c, nullptr); };
  int best = -1;
  double best_cost = std::numeric_limits<double>::infinity();
  for (int i = 0; i < kGrid; ++i) {
    const double v = cost(lo + (hi - lo) * i / (kGrid - 1));
    if (v < best_cost) best_cost = v, best = i;
  }
  if (best < 0) return false;
  const double step = (hi - lo) / (kGrid - 1);
  double a = lo + step * std::max(0, best - 1), b = lo + step * std::min(kGrid - 1, best + 1);
  const double g = 0.5 * (std::sqrt(5.0) - 1);
  double x1 = b - g * (b - a), x2 = a + g * (b - a), f1 = cost(x1), f2 = cost(x2);
  for (int it = 0; it < 40; ++it) {
    if (f1 < f2) {
      b = x2, x2 = x1, f2 = f1, x1 = b - g * (b - a), f1 = cost(x1);
    } else {
      a = x1, x1 = x2, f1 = f2, x2 = a + g * (b - a), f2 = cost(x2);
    }
  }
  const double f = std::exp(0.5 * (a + b));
  if (!std::isfinite(equidistant_fit(frames, f, c, poses)) || poses->size() != frames.size())
    return false;
  *model = CameraModel::pinhole(lens, size.width, size.height, f, f, c.x(), c.y());
  return true;
}

// Ceres logs a warning through glog whenever Levenberg-Marquardt rejects a step (normal for the
// degenerate single views the bootstrap tries). posecal runs inside other people's processes and
// must not write to their stderr: raise glog's threshold to ERROR once, unless
// POSECAL_CERES_LOG is set (a host that uses glog itself can also set FLAGS_minloglevel back).
void quiet_ceres_logging() {
  static std::once_flag once;
  std::call_once(once, [] {
    if (std::getenv("POSECAL_CERES_LOG") == nullptr && FLAGS_minloglevel < google::GLOG_ERROR) {
      FLAGS_minloglevel = google::GLOG_ERROR;
    }
  });
}

// Which intrinsics the options hold fixed.
std::vector<bool> fixed_intrinsics(const CalibrationOptions& options) {
  const LensModel lens = options.lens_model;
  const int n_intr = num_intrinsics(lens);
  const auto& names = intrinsic_names(lens);
  std::vector<bool> fixed(n_intr, false);
  auto fix = [&](const std::string& name) {
    const auto it = std::find(names.begin(), names.end(), name);
    if (it != names.end()) fixed[it - names.begin()] = true;
  };
  if (options.fix_principal_point) fix("cx"), fix("cy");
  if (options.fix_aspect_ratio) fix("fy");
  if (options.zero_tangential) fix("p1"), fix("p2");
  if (options.zero_distortion) {
    for (int i = kNumPinholeParams; i < n_intr; ++i) fixed[i] = true;
  }
  for (const auto& f : options.fixed) fix(f);
  if (std::count(fixed.begin(), fixed.end(), false) == 0) {
    throw Error(ErrorCode::kInvalidArgument, "calibration: every parameter fixed");
  }
  if (options.prior) {
    const auto& pn = options.prior->names;
    for (int i = 0; i < n_intr; ++i) {
      if (!fixed[i] && std::find(pn.begin(), pn.end(), names[i]) == pn.end()) {
        throw Error(ErrorCode::kInvalidArgument,
                    "calibration: the prior does not constrain the free parameter " + names[i]);
      }
    }
  }
  return fixed;
}

// The starting point of the bundle adjustment: the warm start where it fits (frames beyond its
// poses get theirs from PnP), else Zhang's method (a ray model: equidistant_initial()); parameters
// fixed at zero start at zero.
void initial_solution(const std::vector<Observation>& frames, cv::Size image_size, const CalibrationOptions& options,
                      const WarmStart* warm_start, const std::vector<bool>& fixed, CameraModel* model,
                      std::vector<Pose>* poses) {
  const LensModel lens = options.lens_model;
  // With a prior and no warm start: its mean is the start, the poses come from PnP.
  WarmStart from_prior;
  if (options.prior && (warm_start == nullptr || warm_start->model.lens_model() != lens)) {
    from_prior.model = CameraModel(image_size.width, image_size.height, lens, options.prior->mean);
    warm_start = &from_prior;
  }
  if (warm_start != nullptr && warm_start->model.lens_model() == lens &&
      warm_start->model.size() == image_size && warm_start->model.is_valid()) {
    *model = warm_start->model;
    for (size_t i = 0; i < frames.size(); ++i) {
      Pose p;
      if (i < warm_start->poses.size() && warm_start->poses[i].is_finite()) {
        p = warm_start->poses[i];
      } else if (!estimate_pose(*model, frames[i], &p)) {
        throw Error(ErrorCode::kDegenerate,
                    "calibration: cannot find the board pose of frame " + std::to_string(i));
      }
      poses->push_back(p);
    }
  } else if (is_ray_model(lens)) {
    if (!equidistant_initial(frames, image_size, lens, model, poses)) {
      throw Error(ErrorCode::kDegenerate,
                  "calibration: no initial solution (equidistant fit failed): the views do not "
                  "determine the board "
                  "poses, e.g. too few points not on a line");
    }
  } else if (!zhang_initial(frames, image_size, lens, options.fix_principal_point,
                            options.fix_aspect_ratio, model, poses)) {
    throw Error(ErrorCode::kDegenerate,
                "calibration: no initial solution (Zhang's method failed): the views do not "
                "determine the focal length, e.g. they are all parallel to the image plane");
  }
  const auto& names = intrinsic_names(lens);
  for (int i = kNumPinholeParams; i < num_intrinsics(lens); ++i) {
    if (fixed[i] && (options.zero_distortion ||
                     (options.zero_tangential && (names[i] == "p1" || names[i] == "p2")))) {
      model->params()[i] = 0.0;
    }
  }
}

// The bundle adjustment's residual blocks (one per point) and the subset manifold of the fixed
// intrinsics, over the blocks of *solution.
// The prior's block comes last, after every point's (covariance.cpp reads the points' residuals
// first).
void build_problem(const std::vector<Observation>& frames, const CalibrationOptions& options,
                   double aspect, const std::vector<bool>& fixed,
                   calib_internal::Solution* solution, ceres::Problem* problem) {
  const LensModel lens = options.lens_model;
  for (size_t i = 0; i < frames.size(); ++i) {
    for (size_t k = 0; k < frames[i].size(); ++k) {
      problem->AddResidualBlock(make_cost(lens, frames[i].image_points[k], frames[i].board_points[k], aspect),
                                nullptr, solution->intrinsics.data(), solution->rt[i].data());
    }
  }
  if (options.prior) {
    problem->AddResidualBlock(new PriorCost(*options.prior, intrinsic_names(lens)), nullptr,
                              solution->intrinsics.data());
  }
  std::vector<int> fixed_idx;
  for (int i = 0; i < static_cast<int>(fixed.size()); ++i)
    if (fixed[i]) fixed_idx.push_back(i);
  if (!fixed_idx.empty()) {
    problem->SetManifold(solution->intrinsics.data(),
                         new ceres::SubsetManifold(static_cast<int>(fixed.size()), fixed_idx));
  }
}

ceres::Solver::Summary solve_problem(const CalibrationOptions& options, ceres::Problem* problem) {
  ceres::Solver::Options sopt;
  sopt.linear_solver_type = ceres::DENSE_SCHUR;
  sopt.max_num_iterations = options.max_iterations;
  sopt.function_tolerance = options.function_tolerance;
  sopt.parameter_tolerance = options.parameter_tolerance;
  sopt.gradient_tolerance = 1e-14;
  sopt.num_threads = 1;
  sopt.logging_type = ceres::SILENT;
  sopt.minimizer_progress_to_stdout = false;
  ceres::Solver::Summary summary;
  ceres::Solve(sopt, problem, &summary);
  if (summary.termination_type == ceres::FAILURE || !summary.IsSolutionUsable()) {
    throw Error(ErrorCode::kDegenerate,
                "calibration: bundle adjustment failed: " + summary.message);
  }
  return summary;
}

}  // namespace

namespace {

CalibrationResult calibrate_once(const std::vector<Observation>& frames, cv::Size image_size,
                                 const CalibrationOptions& options, const WarmStart* warm_start);

// CalibrationResult::held_covariance: information_with_held() with the calibration's prior and
// tied aspect ratio, inverted with Jacobi scaling (the parameters' units differ by orders of
// magnitude); fy's rows follow fx's when tied, as in the calibration's own covariance. The held
// prior is absolute (kHeldPriorStd whatever the noise), so at unit noise it weighs
// sigma^2 / kHeldPriorStd^2, sigma^2 the residual variance (at least kMinHeldNoiseVariance:
// noise-free data would otherwise leave the held direction unbounded in floating point).
constexpr double kMinHeldNoiseVariance = 1e-6;  // (0.001 px)^2

Eigen::MatrixXd held_covariance(const CalibrationResult& r, const std::vector<Observation>& frames,
                                const CalibrationOptions& options) {
  const double aspect = options.fix_aspect_ratio ? r.model.fy() / r.model.fx() : 0.0;
  const double noise = std::max(r.residual_variance, kMinHeldNoiseVariance);
  std::vector<bool> open;
  Eigen::MatrixXd info =
      information_with_held(r, frames, noise / (kHeldPriorStd * kHeldPriorStd), &open, aspect);
  const std::vector<int> idx = free_intrinsics(open);
  const std::vector<std::string>& names = r.model.param_names();
  if (options.prior) {
    // Its term's J^T J: noise_px^2 times the inverse of its covariance, over the names it holds.
    const IntrinsicsPrior& p = *options.prior;
    const Eigen::MatrixXd pinfo = p.covariance.inverse() * (p.noise_px * p.noise_px);
    const auto at = [&](const std::string& name) {
      const int i = static_cast<int>(std::find(names.begin(), names.end(), name) - names.begin());
      return static_cast<int>(std::find(idx.begin(), idx.end(), i) - idx.begin());
    };
    for (size_t a = 0; a < p.names.size(); ++a) {
      for (size_t b = 0; b < p.names.size(); ++b) {
        const int pa = at(p.names[a]), pb = at(p.names[b]);
        if (pa < info.rows() && pb < info.rows()) info(pa, pb) += pinfo(a, b);
      }
    }
  }
  const Eigen::Index m = info.rows();
  Eigen::VectorXd scale(m);
  for (Eigen::Index a = 0; a < m; ++a)
    scale[a] = info(a, a) > 0 ? 1.0 / std::sqrt(info(a, a)) : 0.0;
  const Eigen::MatrixXd A = scale.asDiagonal() * info * scale.asDiagonal();
  const Eigen::LDLT<Eigen::MatrixXd> ldlt(A);
  const Eigen::MatrixXd C =
      scale.asDiagonal() * ldlt.solve(Eigen::MatrixXd::Identity(m, m)) * scale.asDiagonal();
  const int n = r.model.num_params();
  Eigen::MatrixXd out = Eigen::MatrixXd::Zero(n, n);
  for (Eigen::Index a = 0; a < m; ++a)
    for (Eigen::Index b = 0; b < m; ++b) out(idx[a], idx[b]) = C(a, b);
  if (aspect > 0 && !open[0]) calib_internal::tie_fy_to_fx(aspect, &out);
  if (ldlt.info() != Eigen::Success || !out.allFinite()) {
    throw Error(
        ErrorCode::kDegenerate,
        "calibration: the held parameters' covariance is not finite (" + r.held_reason + ")");
  }
  return out;
}

}  // namespace

CalibrationResult calibrate(const std::vector<Observation>& frames, cv::Size image_size,
                            const CalibrationOptions& options, const WarmStart* warm_start) {
  if (options.hold_if_undetermined.empty())
    return calibrate_once(frames, image_size, options, warm_start);
  // Hold the parameters a rank deficiency names, one at a time, while they are among those that
  // may be held.
  CalibrationOptions held = options;
  std::vector<std::string> names;
  std::string reason;
  const std::vector<std::string>& all = intrinsic_names(options.lens_model);
  while (true) {
    try {
      CalibrationResult r = calibrate_once(frames, image_size, held, warm_start);
      r.held = names;
      r.held_reason = reason;
      if (!names.empty()) r.held_covariance = held_covariance(r, frames, held);
      return r;
    } catch (const calib_internal::Undetermined& e) {
      // The holdable parameter that moves most along the undetermined direction (also when
      // parameters that may not be held dominate it: holding a small part of the direction often
      // removes it; if not, the next round holds the next, until none is left).
      const std::vector<double>& d = e.direction();
      int pick = -1;
      for (int i = 0; i < static_cast<int>(d.size()); ++i) {
        const auto& allowed = options.hold_if_undetermined;
        if (std::find(allowed.begin(), allowed.end(), all[i]) == allowed.end() ||
            std::find(names.begin(), names.end(), all[i]) != names.end()) {
          continue;
        }
        if (pick < 0 || std::abs(d[i]) > std::abs(d[pick])) pick = i;
      }
      if (pick < 0) throw;
      const std::string& name = all[pick];
      names.push_back(name);
      held.fixed.push_back(name);
      if (reason.empty()) reason = e.what();
    } catch (const calib_internal::FocalUnobservable& e) {
      // Every holdable parameter not held yet, at once: the five coefficients' own behaviour.
      const size_t before = names.size();
      for (const std::string& h : options.hold_if_undetermined) {
        if (std::find(names.begin(), names.end(), h) != names.end()) continue;
        names.push_back(h);
        held.fixed.push_back(h);
      }
      if (names.size() == before) throw;
      if (reason.empty()) reason = e.what();
    }
  }
}

namespace {

CalibrationResult calibrate_once(const std::vector<Observation>& frames, cv::Size image_size,
                                 const CalibrationOptions& options, const WarmStart* warm_start) {
  quiet_ceres_logging();
  const auto t0 = std::chrono::steady_clock::now();
  std::string why;
  if (!options.is_valid(&why))
    throw Error(ErrorCode::kInvalidArgument, "calibration options: " + why);
  if (image_size.width <= 0 || image_size.height <= 0) {
    throw Error(ErrorCode::kInvalidArgument, "calibration: image size must be positive");
  }
  check_frames(frames);
  check_prior_size(options, image_size);
  const LensModel lens = options.lens_model;
  const std::vector<bool> fixed = fixed_intrinsics(options);
  const int n_free_intr = static_cast<int>(std::count(fixed.begin(), fixed.end(), false));
  int n_points = 0;
  for (const auto& f : frames) n_points += static_cast<int>(f.size());
  const int n_unknowns = n_free_intr + 6 * static_cast<int>(frames.size());
  const int n_prior = prior_rows(options, fixed);
  if (2 * n_points + n_prior <= n_unknowns) {
    throw Error(ErrorCode::kDegenerate, "calibration: too few points: " + std::to_string(n_points) +
                                            " points give " + std::to_string(2 * n_points) +
                                            " constraints for " + std::to_string(n_unknowns) +
                                            " unknowns");
  }
  CameraModel model;
  std::vector<Pose> poses;
  initial_solution(frames, image_size, options, warm_start, fixed, &model, &poses);
  const double aspect = options.fix_aspect_ratio ? model.fy() / model.fx() : 0.0;

  // Bundle adjustment (paper eq. 3).
  calib_internal::Solution solution{model.params(), std::vector<std::array<double, 6>>(frames.size())};
  for (size_t i = 0; i < frames.size(); ++i) {
    for (int k = 0; k < 3; ++k) {
      solution.rt[i][k] = poses[i].r[k];
      solution.rt[i][3 + k] = poses[i].t[k];
    }
  }
  ceres::Problem::Options popt;
  ceres::Problem problem(popt);
  build_problem(frames, options, aspect, fixed, &solution, &problem);
  const ceres::Solver::Summary summary = solve_problem(options, &problem);
  std::vector<double>& intr = solution.intrinsics;
  if (aspect > 0) intr[1] = intr[0] * aspect;

  CalibrationResult res;
  res.model = CameraModel(image_size.width, image_size.height, lens, intr);
  if (!res.model.is_valid(&why)) {
    throw Error(ErrorCode::kDegenerate, "calibration: solution is not a valid camera: " + why);
  }
  res.fixed = fixed;
  res.num_points = n_points;
  res.num_unknowns = n_unknowns;
  res.iterations = static_cast<int>(summary.iterations.size());
  res.termination = summary.termination_type == ceres::CONVERGENCE ? SolverTermination::kConvergence
                                                                   : SolverTermination::kNoConvergence;
  res.termination_message = summary.message;
  res.poses.resize(frames.size());
  for (size_t i = 0; i < frames.size(); ++i) {
    res.poses[i].r << solution.rt[i][0], solution.rt[i][1], solution.rt[i][2];
    res.poses[i].t << solution.rt[i][3], solution.rt[i][4], solution.rt[i][5];
  }
  calib_internal::CovarianceInput in{&frames,
                                     fixed,
                                     aspect,
                                     n_points,
                                     n_unknowns,
                                     &intrinsic_names(lens),
                                     options.max_relative_focal_std,
                                     n_prior};
  calib_internal::covariance_at_solution(problem, solution, in, &res);
  res.solve_ms =
      std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count();
  return res;
}

}  // namespace

CalibrationResult prior_result(cv::Size image_size, const CalibrationOptions& options) {
  std::string why;
  if (!options.prior) throw Error(ErrorCode::kInvalidArgument, "prior_result: no prior");
  if (!options.is_valid(&why))
    throw Error(ErrorCode::kInvalidArgument, "calibration options: " + why);
  check_prior_size(options, image_size);
  const IntrinsicsPrior& p = *options.prior;
  const LensModel lens = options.lens_model;
  const std::vector<bool> fixed = fixed_intrinsics(options);
  const auto& names = intrinsic_names(lens);
  const int n = num_intrinsics(lens);
  CalibrationResult res;
  res.model = CameraModel(image_size.width, image_size.height, lens, p.mean);
  if (!res.model.is_valid(&why))
    throw Error(ErrorCode::kInvalidArgument, "prior: its mean is not a valid camera: " + why);
  res.fixed = fixed;
  // The free parameters given the fixed ones at the mean: the inverse of the free block of the
  // prior's information matrix.
  const Eigen::MatrixXd info = p.covariance.inverse();
  std::vector<int> at(n, -1);  // position in p.names
  for (int a = 0; a < static_cast<int>(p.names.size()); ++a)
    at[std::find(names.begin(), names.end(), p.names[a]) - names.begin()] = a;
  std::vector<int> free_idx;
  for (int i = 0; i < n; ++i)
    if (!fixed[i]) free_idx.push_back(i);
  const int m = static_cast<int>(free_idx.size());
  Eigen::MatrixXd info_free(m, m);
  for (int a = 0; a < m; ++a)
    for (int b = 0; b < m; ++b) info_free(a, b) = info(at[free_idx[a]], at[free_idx[b]]);
  Eigen::LLT<Eigen::MatrixXd> llt(info_free);
  if (llt.info() != Eigen::Success) {
    throw Error(ErrorCode::kInvalidArgument, "prior: the covariance is not positive definite");
  }
  const Eigen::MatrixXd cov_free = llt.solve(Eigen::MatrixXd::Identity(m, m));
  const double s2 = p.noise_px * p.noise_px;
  res.covariance = Eigen::MatrixXd::Zero(n, n);
  for (int a = 0; a < m; ++a)
    for (int b = 0; b < m; ++b) res.covariance(free_idx[a], free_idx[b]) = cov_free(a, b) / s2;
  res.residual_variance = s2;
  for (int i = 0; i < n; ++i) {
    const double su = std::sqrt(std::max(0.0, res.covariance(i, i)));
    const double v = res.model.params()[i];
    res.std_unit.push_back(su);
    res.std_scaled.push_back(su * p.noise_px);
    res.index_of_dispersion.push_back(v != 0.0 ? su * su / std::abs(v) : su * su);
  }
  res.termination = SolverTermination::kConvergence;
  res.termination_message = "the prior alone";
  return res;
}

}  // namespace posecal
