#include "calib/calibration.hpp"

#include <ceres/ceres.h>
#include <ceres/rotation.h>
#include <glog/logging.h>

#include <Eigen/Dense>
#include <algorithm>
#include <chrono>
#include <limits>
#include <optional>
#include <cmath>
#include <opencv2/calib3d.hpp>
#include <cstdlib>
#include <mutex>
#include <set>

#include "common/error.hpp"

namespace posecal {

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
    if (!(pc[2] > T(1e-9))) return false;  // behind the camera: reject the step
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

}  // namespace

bool estimate_pose(const CameraModel& model, const Observation& frame, Pose* T_cam_board,
                   double* rms_px) {
  if (frame.size() < 4 || frame.image_points.size() != frame.board_points.size()) return false;
  const cv::Mat K(model.camera_matrix());
  const std::vector<double> dist = model.distortion_coefficients();
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
  for (const auto& P : frame.board_points) planar = planar && P.z == 0.0;
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
    if (planar && cv::solvePnP(frame.board_points, frame.image_points, K, dist, rvec, tvec, false, cv::SOLVEPNP_IPPE)) {
      consider(rvec, tvec);
      cv::solvePnPRefineLM(frame.board_points, frame.image_points, K, dist, rvec, tvec);
      consider(rvec, tvec);
    }
  } catch (const cv::Exception&) {
  }
  try {
    cv::Mat rvec, tvec;
    if (cv::solvePnP(frame.board_points, frame.image_points, K, dist, rvec, tvec, false, cv::SOLVEPNP_ITERATIVE)) {
      consider(rvec, tvec);
    }
  } catch (const cv::Exception&) {
  }
  if (!best) return false;
  if (rms_px) *rms_px = best_rms;
  *T_cam_board = *best;
  return true;
}

namespace {

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

}  // namespace

CalibrationResult calibrate(const std::vector<Observation>& frames, cv::Size image_size,
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
  const LensModel lens = options.lens_model;
  const int n_intr = num_intrinsics(lens);
  const auto& names = intrinsic_names(lens);

  // Which intrinsics are free.
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
  const int n_free_intr = static_cast<int>(std::count(fixed.begin(), fixed.end(), false));
  if (n_free_intr == 0)
    throw Error(ErrorCode::kInvalidArgument, "calibration: every parameter fixed");

  int n_points = 0;
  for (const auto& f : frames) n_points += static_cast<int>(f.size());
  const int n_unknowns = n_free_intr + 6 * static_cast<int>(frames.size());
  if (2 * n_points <= n_unknowns) {
    throw Error(ErrorCode::kDegenerate, "calibration: too few points: " + std::to_string(n_points) +
                                            " points give " + std::to_string(2 * n_points) +
                                            " constraints for " + std::to_string(n_unknowns) +
                                            " unknowns");
  }

  // Initial solution.
  CameraModel model;
  std::vector<Pose> poses;
  if (warm_start != nullptr && warm_start->model.lens_model() == lens &&
      warm_start->model.size() == image_size && warm_start->model.is_valid()) {
    model = warm_start->model;
    for (size_t i = 0; i < frames.size(); ++i) {
      Pose p;
      if (i < warm_start->poses.size() && warm_start->poses[i].is_finite()) {
        p = warm_start->poses[i];
      } else if (!estimate_pose(model, frames[i], &p)) {
        throw Error(ErrorCode::kDegenerate,
                    "calibration: cannot find the board pose of frame " + std::to_string(i));
      }
      poses.push_back(p);
    }
  } else {
    if (!zhang_initial(frames, image_size, lens, options.fix_principal_point, options.fix_aspect_ratio,
                       &model, &poses)) {
      throw Error(ErrorCode::kDegenerate,
                  "calibration: no initial solution (Zhang's method failed): the views do not "
                  "determine the focal length, e.g. they are all parallel to the image plane");
    }
  }
  // Parameters that are fixed at zero start at zero.
  for (int i = kNumPinholeParams; i < n_intr; ++i) {
    if (fixed[i] && (options.zero_distortion ||
                     (options.zero_tangential && (names[i] == "p1" || names[i] == "p2")))) {
      model.params()[i] = 0.0;
    }
  }
  const double aspect = options.fix_aspect_ratio ? model.fy() / model.fx() : 0.0;

  // Bundle adjustment (paper eq. 3).
  std::vector<double> intr = model.params();
  std::vector<std::array<double, 6>> rt(frames.size());
  for (size_t i = 0; i < frames.size(); ++i) {
    for (int k = 0; k < 3; ++k) {
      rt[i][k] = poses[i].r[k];
      rt[i][3 + k] = poses[i].t[k];
    }
  }
  ceres::Problem::Options popt;
  ceres::Problem problem(popt);
  for (size_t i = 0; i < frames.size(); ++i) {
    for (size_t k = 0; k < frames[i].size(); ++k) {
      problem.AddResidualBlock(
          make_cost(lens, frames[i].image_points[k], frames[i].board_points[k], aspect), nullptr,
          intr.data(), rt[i].data());
    }
  }
  std::vector<int> fixed_idx;
  for (int i = 0; i < n_intr; ++i)
    if (fixed[i]) fixed_idx.push_back(i);
  if (!fixed_idx.empty()) {
    problem.SetManifold(intr.data(), new ceres::SubsetManifold(n_intr, fixed_idx));
  }
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
  ceres::Solve(sopt, &problem, &summary);
  if (summary.termination_type == ceres::FAILURE || !summary.IsSolutionUsable()) {
    throw Error(ErrorCode::kDegenerate,
                "calibration: bundle adjustment failed: " + summary.message);
  }
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
  res.converged = summary.termination_type == ceres::CONVERGENCE;
  res.poses.resize(frames.size());
  for (size_t i = 0; i < frames.size(); ++i) {
    res.poses[i].r << rt[i][0], rt[i][1], rt[i][2];
    res.poses[i].t << rt[i][3], rt[i][4], rt[i][5];
  }

  // Residuals and Jacobian at the solution. Column order: free intrinsics (tangent space of the
  // subset manifold), then 6 per frame.
  std::vector<double*> blocks{intr.data()};
  for (auto& b : rt) blocks.push_back(b.data());
  ceres::Problem::EvaluateOptions eopt;
  eopt.parameter_blocks = blocks;
  eopt.apply_loss_function = false;
  eopt.num_threads = 1;
  std::vector<double> residuals;
  ceres::CRSMatrix crs;
  double cost = 0;
  if (!problem.Evaluate(eopt, &cost, &residuals, nullptr, &crs)) {
    throw Error(ErrorCode::kInternal, "calibration: cannot evaluate the Jacobian at the solution");
  }
  double ssr = 0;
  size_t r = 0;
  for (size_t i = 0; i < frames.size(); ++i) {
    double fss = 0;
    for (size_t k = 0; k < frames[i].size(); ++k, r += 2) {
      fss += residuals[r] * residuals[r] + residuals[r + 1] * residuals[r + 1];
    }
    ssr += fss;
    res.frame_rms_px.push_back(std::sqrt(fss / static_cast<double>(frames[i].size())));
  }
  res.rms_px = std::sqrt(ssr / n_points);
  res.residual_variance = ssr / std::max(1, 2 * n_points - n_unknowns);

  // J^T J, accumulated row by row from the sparse Jacobian.
  const int n_cols = crs.num_cols;
  Eigen::MatrixXd JtJ = Eigen::MatrixXd::Zero(n_cols, n_cols);
  for (int row = 0; row < crs.num_rows; ++row) {
    const int b = crs.rows[row], e = crs.rows[row + 1];
    for (int a = b; a < e; ++a) {
      const double va = crs.values[a];
      const int ca = crs.cols[a];
      for (int c = a; c < e; ++c) JtJ(ca, crs.cols[c]) += va * crs.values[c];
    }
  }
  JtJ = JtJ.selfadjointView<Eigen::Upper>();
  // Pseudo-inverse with Jacobi scaling so parameters of different units (pixels, radians,
  // metres, unitless k) are compared on one scale; eigenvalues below a relative tolerance are
  // treated as zero (the (.)^+ of eq. 5).
  Eigen::VectorXd scale(n_cols);
  for (int i = 0; i < n_cols; ++i) scale[i] = JtJ(i, i) > 0 ? 1.0 / std::sqrt(JtJ(i, i)) : 0.0;
  const Eigen::MatrixXd A = scale.asDiagonal() * JtJ * scale.asDiagonal();
  Eigen::SelfAdjointEigenSolver<Eigen::MatrixXd> eig(A);
  const Eigen::VectorXd& ev = eig.eigenvalues();
  const double tol = 1e-12 * std::max(1.0, ev.maxCoeff());
  Eigen::VectorXd inv_ev(ev.size());
  for (int i = 0; i < ev.size(); ++i) {
    if (ev[i] > tol) {
      inv_ev[i] = 1.0 / ev[i];
    } else {
      inv_ev[i] = 0.0;
      ++res.rank_deficiency;
    }
  }
  for (int i = 0; i < n_cols; ++i)
    if (scale[i] == 0) ++res.rank_deficiency;
  const Eigen::MatrixXd Ainv =
      eig.eigenvectors() * inv_ev.asDiagonal() * eig.eigenvectors().transpose();
  const Eigen::MatrixXd cov_tangent = scale.asDiagonal() * Ainv * scale.asDiagonal();

  // Back to the ambient order (all intrinsics, then 6 per frame); fixed rows/columns stay 0.
  const int n_amb = n_intr + 6 * static_cast<int>(frames.size());
  std::vector<int> amb_of_tangent;
  for (int i = 0; i < n_intr; ++i)
    if (!fixed[i]) amb_of_tangent.push_back(i);
  for (int i = n_intr; i < n_amb; ++i) amb_of_tangent.push_back(i);
  if (static_cast<int>(amb_of_tangent.size()) != n_cols) {
    throw Error(ErrorCode::kInternal, "calibration: Jacobian has an unexpected column count");
  }
  res.covariance = Eigen::MatrixXd::Zero(n_amb, n_amb);
  for (int a = 0; a < n_cols; ++a)
    for (int b = 0; b < n_cols; ++b)
      res.covariance(amb_of_tangent[a], amb_of_tangent[b]) = cov_tangent(a, b);
  if (aspect > 0) {
    // fy = aspect * fx: its variance follows from fx's.
    res.covariance.row(1) = res.covariance.row(0) * aspect;
    res.covariance.col(1) = res.covariance.col(0) * aspect;
    res.covariance(1, 1) = res.covariance(0, 0) * aspect * aspect;
  }

  const double sigma = std::sqrt(res.residual_variance);
  for (int i = 0; i < n_intr; ++i) {
    const double s_unit = std::sqrt(std::max(0.0, res.covariance(i, i)));
    const double value = res.model.params()[i];
    res.std_unit.push_back(s_unit);
    res.std_scaled.push_back(s_unit * sigma);
    // Index of dispersion sigma^2 / |C| (paper §4.1; sigma^2 where C = 0).
    res.index_of_dispersion.push_back(value != 0.0 ? s_unit * s_unit / std::abs(value)
                                                   : s_unit * s_unit);
  }

  // Degeneracy: an unobservable direction, or a focal length the views cannot pin down.
  if (res.rank_deficiency > 0) {
    // Name the intrinsic that dominates the weakest direction.
    int worst = 0;
    double best = -1;
    const Eigen::VectorXd v0 = eig.eigenvectors().col(0);
    for (int a = 0; a < n_cols; ++a) {
      if (amb_of_tangent[a] < n_intr && std::abs(v0[a]) > best) {
        best = std::abs(v0[a]);
        worst = amb_of_tangent[a];
      }
    }
    throw Error(ErrorCode::kDegenerate,
                "calibration: the views do not determine every parameter (rank deficiency " +
                    std::to_string(res.rank_deficiency) + ", weakest: " + names[worst] +
                    "); add views tilted towards the camera");
  }
  for (int i : {0, 1}) {
    if (fixed[i] && aspect == 0) continue;
    const double rel = res.std_unit[i] / res.model.params()[i];
    if (!(rel <= options.max_relative_focal_std)) {
      throw Error(ErrorCode::kDegenerate,
                  "calibration: focal length " + names[i] + " is unobservable (relative std " +
                      std::to_string(rel) +
                      " at 1 px noise): the views are too close to parallel to the image plane");
    }
  }
  for (int i = 0; i < n_intr; ++i) {
    if (!std::isfinite(res.std_unit[i])) {
      throw Error(ErrorCode::kDegenerate,
                  "calibration: covariance of " + names[i] + " is not finite");
    }
  }
  res.solve_ms =
      std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count();
  return res;
}

}  // namespace posecal
