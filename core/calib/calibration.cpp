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

// Reprojection residual of one board point (paper eq. 3): pi(P; R, t, C) - p.
template <int N>
struct ReprojectionCost {
  LensModel model;
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
    project_generic(model, params, pc, uv);
    residual[0] = uv[0] - T(u);
    residual[1] = uv[1] - T(v);
    return true;
  }
};

ceres::CostFunction* make_cost(LensModel model, const cv::Point2d& p, const cv::Point3d& P,
                               double aspect) {
  switch (model) {
    case LensModel::kOpenCV5:
      return new ceres::AutoDiffCostFunction<ReprojectionCost<9>, 2, 9, 6>(
          new ReprojectionCost<9>{model, p.x, p.y, P.x, P.y, P.z, aspect});
  }
  throw Error(ErrorCode::kInternal, "no cost function for lens model");
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
bool zhang_initial(const std::vector<Observation>& frames, cv::Size size, bool fix_pp,
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
  *model = CameraModel::opencv5(size.width, size.height, K.at<double>(0, 0), K.at<double>(1, 1),
                                K.at<double>(0, 2), K.at<double>(1, 2), {0, 0, 0, 0, 0});
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
    if (!zhang_initial(frames, image_size, options.fix_principal_point, options.fix_aspect_ratio,
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

namespace {

// Projection of a camera-frame point under the OpenCV 5-coefficient model (project_generic) with
// its derivatives: Jc = d(u, v)/d(p_cam) and Ji = d(u, v)/d(fx fy cx cy k1 k2 p1 p2 k3), a 2x9
// column-major array (Eigen's layout). By hand, a few times faster than forward-mode Jets;
// tests compare frame_information() with central differences.
[[gnu::always_inline]] inline void opencv5_jacobians(const double* q, const Eigen::Vector3d& pc, double* u, double* v,
                       Eigen::Matrix<double, 2, 3>* Jc, double* Ji) {
  const double fx = q[0], fy = q[1], k1 = q[4], k2 = q[5], p1 = q[6], p2 = q[7], k3 = q[8];
  const double iz = 1.0 / pc.z();
  const double x = pc.x() * iz, y = pc.y() * iz;
  const double x2 = x * x, y2 = y * y, xy = x * y, r2 = x2 + y2, r4 = r2 * r2, r6 = r4 * r2;
  const double radial = 1 + k1 * r2 + k2 * r4 + k3 * r6;
  const double dradial = k1 + 2 * k2 * r2 + 3 * k3 * r4;  // d radial / d r2
  const double xd = x * radial + 2 * p1 * xy + p2 * (r2 + 2 * x2);
  const double yd = y * radial + p1 * (r2 + 2 * y2) + 2 * p2 * xy;
  *u = fx * xd + q[2];
  *v = fy * yd + q[3];
  // d(xd, yd)/d(x, y)
  const double a = radial + 2 * x2 * dradial + 2 * p1 * y + 6 * p2 * x;
  const double b = 2 * xy * dradial + 2 * p1 * x + 2 * p2 * y;
  const double d = radial + 2 * y2 * dradial + 6 * p1 * y + 2 * p2 * x;
  // d(x, y)/d(p_cam) = [[1/z, 0, -x/z], [0, 1/z, -y/z]]
  (*Jc)(0, 0) = fx * a * iz, (*Jc)(0, 1) = fx * b * iz, (*Jc)(0, 2) = -fx * (a * x + b * y) * iz;
  (*Jc)(1, 0) = fy * b * iz, (*Jc)(1, 1) = fy * d * iz, (*Jc)(1, 2) = -fy * (b * x + d * y) * iz;
  // Column-major 2x9: element (r, k) at Ji[2 k + r].
  const double J[2][9] = {{xd, 0, 1, 0, fx * x * r2, fx * x * r4, fx * 2 * xy, fx * (r2 + 2 * x2), fx * x * r6},
                          {0, yd, 0, 1, fy * y * r2, fy * y * r4, fy * (r2 + 2 * y2), fy * 2 * xy, fy * y * r6}};
  for (int k = 0; k < 9; ++k) Ji[2 * k] = J[0][k], Ji[2 * k + 1] = J[1][k];
}

// frame_information() for models with at most kNParams intrinsics. The pose enters through a
// left perturbation of the board points in the camera frame, d(p_cam) = [-[R P]x | I] (dw, dt):
// the Schur complement onto the intrinsics does not depend on how the eliminated pose is
// parametrised, so this equals the complement for the rotation vector, without differentiating
// the rotation. Forward-mode derivatives only over p_cam and the intrinsics.
// `weights` (optional, one per point) scales each point's contribution. Returns false (S
// untouched) if the pose is unobservable from the points in view.
template <int kNParams>
[[gnu::always_inline]] inline bool frame_information_full(const CameraModel& model, const Eigen::Matrix3d& R, const Eigen::Vector3d& t,
                            const std::vector<cv::Point3d>& board_points, const double* weights,
                            Eigen::Matrix<double, kNParams, kNParams>* S) {
  using Jet = ceres::Jet<double, 3 + kNParams>;
  using MatA = Eigen::Matrix<double, kNParams, kNParams>;
  using MatB = Eigen::Matrix<double, kNParams, 6>;
  const int n = model.num_params();
  MatA A = MatA::Zero();
  MatB B = MatB::Zero();
  Eigen::Matrix<double, 6, 6> D = Eigen::Matrix<double, 6, 6>::Zero();
  const bool analytic = model.lens_model() == LensModel::kOpenCV5 && kNParams == 9;
  Jet intr[kNParams];
  if (!analytic)
    for (int i = 0; i < n; ++i) intr[i] = Jet(model.params()[i], 3 + i);
  Eigen::Matrix<double, 2, kNParams> Ji = Eigen::Matrix<double, 2, kNParams>::Zero();
  Eigen::Matrix<double, 2, 3> Jc;
  Eigen::Matrix<double, 3, 6> dpc = Eigen::Matrix<double, 3, 6>::Zero();
  dpc.template rightCols<3>().setIdentity();
  double M[15][15] = {};  // kNParams == 9: [A B; B^T D], upper triangle
  for (size_t p = 0; p < board_points.size(); ++p) {
    const cv::Point3d& P = board_points[p];
    const Eigen::Vector3d RP = R * Eigen::Vector3d(P.x, P.y, P.z);
    const Eigen::Vector3d pc = RP + t;
    if (!(pc.z() > 1e-9)) continue;
    double u, v;
    if (analytic) {
      opencv5_jacobians(model.params().data(), pc, &u, &v, &Jc, Ji.data());
    } else {
      const Jet jpc[3] = {Jet(pc.x(), 0), Jet(pc.y(), 1), Jet(pc.z(), 2)};
      Jet uv[2];
      project_generic(model.lens_model(), intr, jpc, uv);
      u = uv[0].a, v = uv[1].a;
      for (int r = 0; r < 2; ++r) {
        for (int k = 0; k < 3; ++k) Jc(r, k) = uv[r].v[k];
        for (int k = 0; k < n; ++k) Ji(r, k) = uv[r].v[3 + k];
      }
    }
    if (!(u >= -0.5 && u <= model.width() - 0.5 && v >= -0.5 && v <= model.height() - 0.5)) {
      continue;  // not observed
    }
    // d(R P)/dw for R <- exp([w]x) R is -[R P]x.
    dpc(0, 1) = RP.z(), dpc(0, 2) = -RP.y();
    dpc(1, 0) = -RP.z(), dpc(1, 2) = RP.x();
    dpc(2, 0) = RP.y(), dpc(2, 1) = -RP.x();
    Eigen::Matrix<double, 2, 6> Jp = Jc * dpc;
    if (weights) {
      const double sw = std::sqrt(weights[p]);
      Ji *= sw;
      Jp *= sw;
    }
    if (kNParams == 9) {
      // [Ji | Jp] into the upper triangle of a 15x15 sum: symmetric, half the work.
      double J0[15], J1[15];
      for (int k = 0; k < kNParams; ++k) J0[k] = Ji(0, k), J1[k] = Ji(1, k);
      for (int k = 0; k < 6; ++k) J0[kNParams + k] = Jp(0, k), J1[kNParams + k] = Jp(1, k);
      for (int a = 0; a < 15; ++a)
        for (int b = a; b < 15; ++b) M[a][b] += J0[a] * J0[b] + J1[a] * J1[b];
      continue;
    }
    // Coefficient-based products: for these sizes Eigen would otherwise call its GEMM kernel,
    // several times slower here.
    A.noalias() += Ji.transpose().lazyProduct(Ji);
    B.noalias() += Ji.transpose().lazyProduct(Jp);
    D.noalias() += Jp.transpose().lazyProduct(Jp);
  }
  if (kNParams == 9) {
    for (int a = 0; a < 15; ++a) {
      for (int b = a; b < 15; ++b) {
        if (b < kNParams) {
          A(a, b) = A(b, a) = M[a][b];
        } else if (a < kNParams) {
          B(a, b - kNParams) = M[a][b];
        } else {
          D(a - kNParams, b - kNParams) = D(b - kNParams, a - kNParams) = M[a][b];
        }
      }
    }
  }
  if (!(D.trace() > 0)) return false;
  // S = A - B D^-1 B^T, by D = L L^T and X = L^-1 B^T: S = A - X^T X.
  const Eigen::LLT<Eigen::Matrix<double, 6, 6>> llt(D);
  if (llt.info() == Eigen::Success) {
    const Eigen::Matrix<double, 6, kNParams> X = llt.matrixL().solve(B.transpose());
    *S = A - X.transpose().lazyProduct(X);
    return true;
  }
  const Eigen::LDLT<Eigen::Matrix<double, 6, 6>> ldlt(D);  // semi-definite: few points in view
  if (ldlt.info() != Eigen::Success) return false;
  const MatB BDinv = ldlt.solve(B.transpose()).transpose();
  *S = A - BDinv.lazyProduct(B.transpose());
  return true;
}

// The 9-intrinsic instance, compiled twice: for x86-64-v3 CPUs (AVX2, FMA; chosen at load time where
// available: the accumulation over points is most of the cost of screening view candidates) and
// for the baseline.
__attribute__((target_clones("arch=x86-64-v3", "default"))) bool frame_information_full9(
    const CameraModel& model, const Eigen::Matrix3d& R, const Eigen::Vector3d& t,
    const std::vector<cv::Point3d>& board_points, const double* weights, Eigen::Matrix<double, 9, 9>* S) {
  return frame_information_full<9>(model, R, t, board_points, weights, S);
}

template <int kNParams>
Eigen::MatrixXd frame_information_impl(const CameraModel& model, const Pose& T_cam_board,
                                       const std::vector<cv::Point3d>& board_points,
                                       const std::vector<bool>& fixed) {
  // Keep the free parameters, in order.
  std::vector<int> free_idx;
  for (int i = 0; i < model.num_params(); ++i)
    if (!fixed[i]) free_idx.push_back(i);
  const int m = static_cast<int>(free_idx.size());
  Eigen::Matrix<double, kNParams, kNParams> S;
  bool seen;
  if constexpr (kNParams == 9) {
    seen = frame_information_full9(model, T_cam_board.R(), T_cam_board.t, board_points, nullptr, &S);
  } else {
    seen = frame_information_full<kNParams>(model, T_cam_board.R(), T_cam_board.t, board_points, nullptr, &S);
  }
  if (!seen) {
    return Eigen::MatrixXd::Zero(m, m);
  }
  Eigen::MatrixXd out(m, m);
  for (int a = 0; a < m; ++a)
    for (int b = 0; b < m; ++b) out(a, b) = S(free_idx[a], free_idx[b]);
  return out;
}

}  // namespace

Eigen::MatrixXd frame_information(const CameraModel& model, const Pose& T_cam_board,
                                  const std::vector<cv::Point3d>& board_points,
                                  const std::vector<bool>& fixed) {
  const int n = model.num_params();
  if (static_cast<int>(fixed.size()) != n) throw Error(ErrorCode::kInvalidArgument, "frame_information: fixed size");
  if (n <= 9) return frame_information_impl<9>(model, T_cam_board, board_points, fixed);
  return frame_information_impl<kMaxIntrinsics>(model, T_cam_board, board_points, fixed);
}

Eigen::MatrixXd frame_information(const CameraModel& model, const Pose& T_cam_board,
                                  const std::vector<cv::Point3d>& board_points,
                                  const std::vector<double>& weights, const std::vector<bool>& fixed) {
  const int n = model.num_params();
  if (static_cast<int>(fixed.size()) != n) throw Error(ErrorCode::kInvalidArgument, "frame_information: fixed size");
  if (weights.size() != board_points.size()) throw Error(ErrorCode::kInvalidArgument, "frame_information: one weight per point");
  if (n > 9) throw Error(ErrorCode::kInvalidArgument, "frame_information: weighted points need at most 9 intrinsics");
  for (double w : weights)
    if (!(w >= 0 && std::isfinite(w))) throw Error(ErrorCode::kInvalidArgument, "frame_information: weights must be finite and >= 0");
  std::vector<int> free_idx;
  for (int i = 0; i < n; ++i)
    if (!fixed[i]) free_idx.push_back(i);
  const int m = static_cast<int>(free_idx.size());
  Eigen::Matrix<double, 9, 9> S;
  if (!frame_information_full9(model, T_cam_board.R(), T_cam_board.t, board_points, weights.data(), &S)) {
    return Eigen::MatrixXd::Zero(m, m);
  }
  Eigen::MatrixXd out(m, m);
  for (int a = 0; a < m; ++a)
    for (int b = 0; b < m; ++b) out(a, b) = S(free_idx[a], free_idx[b]);
  return out;
}

bool frame_information_all9(const CameraModel& model, const Eigen::Matrix3d& R_cam_board, const Eigen::Vector3d& t_cam_board,
                            const std::vector<cv::Point3d>& board_points, const double* weights,
                            Eigen::Matrix<double, 9, 9>* S) {
  if (model.num_params() > 9) throw Error(ErrorCode::kInvalidArgument, "frame_information_all9: more than 9 intrinsics");
  return frame_information_full9(model, R_cam_board, t_cam_board, board_points, weights, S);
}

namespace {

// Nodes (offsets from the mean, in units of the spacing) and weights of the `nodes`-point Gauss
// rule for the n equally spaced values 0 .. n-1: it matches their moments up to degree
// 2 nodes - 1 (sigma^2 = (n^2-1)/12, fourth central moment (n^2-1)(3n^2-7)/240).
void discrete_gauss(int n, int nodes, std::vector<double>* x, std::vector<double>* w) {
  const double nn = n;
  const double var = (nn * nn - 1) / 12.0;
  if (nodes == 2) {
    *x = {-std::sqrt(var), std::sqrt(var)};
    *w = {nn / 2, nn / 2};
    return;
  }
  const double mu4 = (nn * nn - 1) * (3 * nn * nn - 7) / 240.0;
  const double a = std::sqrt(mu4 / var), w1 = nn * var * var / (2 * mu4);
  *x = {-a, 0.0, a};
  *w = {w1, nn - 2 * w1, w1};
}

// Sorted distinct values of v (within tol); false unless they are equally spaced.
bool regular_values(std::vector<double> v, double tol, std::vector<double>* out) {
  std::sort(v.begin(), v.end());
  out->clear();
  for (double x : v)
    if (out->empty() || x - out->back() > tol) out->push_back(x);
  if (out->size() < 2) return true;
  const double h = ((*out)[out->size() - 1] - (*out)[0]) / static_cast<double>(out->size() - 1);
  for (size_t i = 0; i < out->size(); ++i)
    if (std::abs((*out)[i] - ((*out)[0] + h * static_cast<double>(i))) > tol) return false;
  return true;
}

}  // namespace

void corner_quadrature(const std::vector<cv::Point3d>& corners, int nodes_x, int nodes_y, std::vector<cv::Point3d>* points,
                       std::vector<double>* weights) {
  for (int nodes : {nodes_x, nodes_y})
    if (nodes != 2 && nodes != 3) throw Error(ErrorCode::kInvalidArgument, "corner_quadrature: nodes must be 2 or 3");
  *points = corners;
  weights->assign(corners.size(), 1.0);
  if (corners.empty()) return;
  double extent = 0;
  std::vector<double> xs, ys;
  for (const cv::Point3d& c : corners) {
    extent = std::max({extent, std::abs(c.x), std::abs(c.y)});
    xs.push_back(c.x);
    ys.push_back(c.y);
    if (c.z != corners[0].z) return;
  }
  const double tol = 1e-9 * std::max(extent, 1e-12);
  std::vector<double> ux, uy;
  if (!regular_values(xs, tol, &ux) || !regular_values(ys, tol, &uy)) return;
  const int nx = static_cast<int>(ux.size()), ny = static_cast<int>(uy.size());
  if (nx <= nodes_x || ny <= nodes_y || static_cast<size_t>(nx) * ny != corners.size()) return;
  std::set<std::pair<long long, long long>> cells;  // every grid cell taken exactly once
  const double hx = (ux.back() - ux.front()) / (nx - 1), hy = (uy.back() - uy.front()) / (ny - 1);
  for (const cv::Point3d& c : corners) cells.emplace(std::llround((c.x - ux[0]) / hx), std::llround((c.y - uy[0]) / hy));
  if (cells.size() != corners.size()) return;
  std::vector<double> gx, wx, gy, wy;
  discrete_gauss(nx, nodes_x, &gx, &wx);
  discrete_gauss(ny, nodes_y, &gy, &wy);
  const double mx = 0.5 * (ux.front() + ux.back()), my = 0.5 * (uy.front() + uy.back());
  points->clear();
  weights->clear();
  for (int j = 0; j < nodes_y; ++j) {
    for (int i = 0; i < nodes_x; ++i) {
      points->emplace_back(mx + gx[i] * hx, my + gy[j] * hy, corners[0].z);
      weights->push_back(wx[i] * wy[j]);
    }
  }
}

Eigen::MatrixXd intrinsics_information(const CalibrationResult& result) {
  std::vector<int> free_idx;
  for (size_t i = 0; i < result.fixed.size(); ++i)
    if (!result.fixed[i]) free_idx.push_back(static_cast<int>(i));
  const int m = static_cast<int>(free_idx.size());
  Eigen::MatrixXd C(m, m);
  for (int a = 0; a < m; ++a)
    for (int b = 0; b < m; ++b) C(a, b) = result.covariance(free_idx[a], free_idx[b]);
  return C.ldlt().solve(Eigen::MatrixXd::Identity(m, m));
}

Eigen::MatrixXd projection_gram(const CameraModel& model, const std::vector<bool>& fixed, int cols, int rows) {
  const int n = model.num_params();
  if (static_cast<int>(fixed.size()) != n) throw Error(ErrorCode::kInvalidArgument, "projection_gram: fixed size");
  if (cols < 1 || rows < 1) throw Error(ErrorCode::kInvalidArgument, "projection_gram: grid must be >= 1x1");
  std::vector<int> free_idx;
  for (int i = 0; i < n; ++i)
    if (!fixed[i]) free_idx.push_back(i);
  const int m = static_cast<int>(free_idx.size());
  Eigen::MatrixXd G = Eigen::MatrixXd::Zero(m, m);
  Eigen::MatrixXd Jf(2, m);
  int count = 0;
  for (int j = 0; j < rows; ++j) {
    for (int i = 0; i < cols; ++i) {
      const Eigen::Vector2d p((i + 0.5) * model.width() / cols - 0.5, (j + 0.5) * model.height() / rows - 0.5);
      Eigen::Vector2d xn, uv;
      Eigen::Matrix<double, 2, Eigen::Dynamic> J;
      if (!model.unproject(p, &xn)) continue;
      if (model.lens_model() == LensModel::kOpenCV5 && n == 9) {
        Eigen::Matrix<double, 2, 3> Jc;
        J.resize(2, 9);
        opencv5_jacobians(model.params().data(), Eigen::Vector3d(xn.x(), xn.y(), 1.0), &uv.x(), &uv.y(), &Jc, J.data());
      } else if (!model.project(Eigen::Vector3d(xn.x(), xn.y(), 1.0), &uv, nullptr, &J)) {
        continue;
      }
      for (int k = 0; k < m; ++k) Jf.col(k) = J.col(free_idx[k]);
      G.noalias() += Jf.transpose() * Jf;
      ++count;
    }
  }
  if (count > 0) G /= count;
  return G;
}

}  // namespace posecal
