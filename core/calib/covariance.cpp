// The covariance of the calibration (paper eq. 5): backward transport of the point noise through
// the Jacobian at the solution, as a Jacobi-scaled pseudo-inverse, with the residual statistics
// that scale it and the checks that reject a solution the views cannot determine.
#include <Eigen/Dense>
#include <algorithm>
#include <cmath>

#include "calib/solve_internal.hpp"
#include "common/error.hpp"

namespace posecal::calib_internal {

namespace {

// Residuals and the sparse Jacobian at the solution. Column order: free intrinsics (tangent space
// of the subset manifold), then 6 per frame.
void evaluate_at_solution(ceres::Problem& problem, Solution& solution, std::vector<double>* residuals,
                          ceres::CRSMatrix* crs) {
  ceres::Problem::EvaluateOptions eopt;
  eopt.parameter_blocks = solution.blocks();
  eopt.apply_loss_function = false;
  eopt.num_threads = 1;
  double cost = 0;
  if (!problem.Evaluate(eopt, &cost, residuals, nullptr, crs)) {
    throw Error(ErrorCode::kInternal, "calibration: cannot evaluate the Jacobian at the solution");
  }
}

// eps_res overall and per frame, and the residual variance sigma^2 = SSR / (2N + prior rows -
// unknowns), SSR over the points only.
void residual_statistics(const std::vector<double>& residuals, const CovarianceInput& in, CalibrationResult* res) {
  const std::vector<Observation>& frames = *in.frames;
  double ssr = 0;
  size_t r = 0;
  for (size_t i = 0; i < frames.size(); ++i) {
    double fss = 0;
    for (size_t k = 0; k < frames[i].size(); ++k, r += 2) {
      fss += residuals[r] * residuals[r] + residuals[r + 1] * residuals[r + 1];
    }
    ssr += fss;
    res->frame_rms_px.push_back(std::sqrt(fss / static_cast<double>(frames[i].size())));
  }
  res->rms_px = std::sqrt(ssr / in.num_points);
  // A prior's rows are pseudo-observations: they count towards the degrees of freedom.
  res->residual_variance = ssr / std::max(1, 2 * in.num_points + in.prior_rows - in.num_unknowns);
}

// J^T J, accumulated row by row from the sparse Jacobian.
Eigen::MatrixXd normal_matrix(const ceres::CRSMatrix& crs) {
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
  return JtJ;
}

// The pseudo-inverse of J^T J with Jacobi scaling, so that parameters of different units (pixels,
// radians, metres, unitless k) are compared on one scale; eigenvalues below a relative tolerance
// are treated as zero (the (.)^+ of eq. 5). *weakest: the eigenvector of the smallest eigenvalue
// (scaled coordinates).
Eigen::MatrixXd scaled_pseudo_inverse(const Eigen::MatrixXd& JtJ, int* rank_deficiency, Eigen::VectorXd* weakest) {
  const int n_cols = static_cast<int>(JtJ.rows());
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
      ++*rank_deficiency;
    }
  }
  for (int i = 0; i < n_cols; ++i)
    if (scale[i] == 0) ++*rank_deficiency;
  const Eigen::MatrixXd Ainv =
      eig.eigenvectors() * inv_ev.asDiagonal() * eig.eigenvectors().transpose();
  *weakest = eig.eigenvectors().col(0);
  return scale.asDiagonal() * Ainv * scale.asDiagonal();
}

// Back to the ambient order (all intrinsics, then 6 per frame); fixed rows/columns stay 0. The
// tangent-space column of each ambient parameter goes into *amb_of_tangent.
Eigen::MatrixXd ambient_covariance(const Eigen::MatrixXd& cov_tangent, const CovarianceInput& in,
                                   std::vector<int>* amb_of_tangent) {
  const int n_intr = static_cast<int>(in.fixed.size());
  const int n_amb = n_intr + 6 * static_cast<int>(in.frames->size());
  for (int i = 0; i < n_intr; ++i)
    if (!in.fixed[i]) amb_of_tangent->push_back(i);
  for (int i = n_intr; i < n_amb; ++i) amb_of_tangent->push_back(i);
  const int n_cols = static_cast<int>(cov_tangent.rows());
  if (static_cast<int>(amb_of_tangent->size()) != n_cols) {
    throw Error(ErrorCode::kInternal, "calibration: Jacobian has an unexpected column count");
  }
  Eigen::MatrixXd cov = Eigen::MatrixXd::Zero(n_amb, n_amb);
  for (int a = 0; a < n_cols; ++a)
    for (int b = 0; b < n_cols; ++b) cov((*amb_of_tangent)[a], (*amb_of_tangent)[b]) = cov_tangent(a, b);
  if (in.aspect > 0) tie_fy_to_fx(in.aspect, &cov);
  return cov;
}

// Degeneracy: an unobservable direction, or a focal length the views cannot pin down.
void check_determined(const CalibrationResult& res, const CovarianceInput& in, const Eigen::VectorXd& weakest,
                      const std::vector<int>& amb_of_tangent) {
  const std::vector<std::string>& names = *in.names;
  const int n_intr = static_cast<int>(in.fixed.size());
  if (res.rank_deficiency > 0) {
    // Name the intrinsic that dominates the weakest direction.
    int worst = 0;
    double best = -1;
    std::vector<double> direction(n_intr, 0.0);
    for (int a = 0; a < static_cast<int>(amb_of_tangent.size()); ++a) {
      if (amb_of_tangent[a] < n_intr) direction[amb_of_tangent[a]] = weakest[a];
      if (amb_of_tangent[a] < n_intr && std::abs(weakest[a]) > best) {
        best = std::abs(weakest[a]);
        worst = amb_of_tangent[a];
      }
    }
    throw Undetermined("calibration: the views do not determine every parameter (rank deficiency " +
                           std::to_string(res.rank_deficiency) + ", weakest: " + names[worst] +
                           "); add views tilted towards the camera",
                       std::move(direction));
  }
  for (int i : {0, 1}) {
    if (in.fixed[i] && in.aspect == 0) continue;
    const double rel = res.std_unit[i] / res.model.params()[i];
    if (!(rel <= in.max_relative_focal_std)) {
      throw FocalUnobservable(
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
}

}  // namespace

void tie_fy_to_fx(double aspect, Eigen::MatrixXd* cov) {
  cov->row(1) = cov->row(0) * aspect;
  cov->col(1) = cov->col(0) * aspect;
  (*cov)(1, 1) = (*cov)(0, 0) * aspect * aspect;
}

void covariance_at_solution(ceres::Problem& problem, Solution& solution, const CovarianceInput& in,
                            CalibrationResult* res) {
  std::vector<double> residuals;
  ceres::CRSMatrix crs;
  evaluate_at_solution(problem, solution, &residuals, &crs);
  residual_statistics(residuals, in, res);
  Eigen::VectorXd weakest;
  const Eigen::MatrixXd cov_tangent = scaled_pseudo_inverse(normal_matrix(crs), &res->rank_deficiency, &weakest);
  std::vector<int> amb_of_tangent;
  res->covariance = ambient_covariance(cov_tangent, in, &amb_of_tangent);
  const double sigma = std::sqrt(res->residual_variance);
  for (int i = 0; i < static_cast<int>(in.fixed.size()); ++i) {
    const double s_unit = std::sqrt(std::max(0.0, res->covariance(i, i)));
    const double value = res->model.params()[i];
    res->std_unit.push_back(s_unit);
    res->std_scaled.push_back(s_unit * sigma);
    // Index of dispersion sigma^2 / |C| (paper §4.1; sigma^2 where C = 0).
    res->index_of_dispersion.push_back(value != 0.0 ? s_unit * s_unit / std::abs(value) : s_unit * s_unit);
  }
  check_determined(*res, in, weakest, amb_of_tangent);
}

}  // namespace posecal::calib_internal
