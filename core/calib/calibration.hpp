// Calibration: Zhang's initial solution (OpenCV) refined by a Ceres bundle adjustment over the
// intrinsics and every frame's board pose (solve.cpp), with the parameter covariance of the
// paper's eq. 5 (covariance.cpp). Pose estimation of one view: pose_estimation.hpp; the
// information maths of pose selection: information.hpp.
#pragma once

#include <Eigen/Core>
#include <optional>
#include <string>
#include <vector>

#include "lens/camera_model.hpp"
#include "lens/geometry.hpp"
#include "board/board.hpp"

namespace posecal {

// One frame's correspondences (a Detection without the bookkeeping).
struct Observation {
  std::vector<int> ids;
  std::vector<cv::Point2d> image_points;
  std::vector<cv::Point3d> board_points;
  size_t size() const { return image_points.size(); }
  static Observation from(const Detection& d) { return {d.ids, d.image_points, d.board_points}; }
};

// A Gaussian prior on the intrinsics (docs/math.md, "The fleet prior"): before any view, the
// parameters `names` are distributed as N(mean, covariance), e.g. the passed units of a
// production line (records/fleet.hpp). calibrate() then minimises
//   sum |p - pi(P)|^2 + noise_px^2 (x - mean)^T covariance^-1 (x - mean),
// the negative log posterior of corners with noise noise_px (the MAP estimate), starts from the
// mean when it has no warm start, and its covariance is the posterior's. Every free intrinsic
// must be among `names`.
struct IntrinsicsPrior {
  std::vector<double> mean;        // every intrinsic of the lens model, in its order
  std::vector<std::string> names;  // the parameters the prior constrains
  Eigen::MatrixXd covariance;      // over `names`, in their order; positive definite
  double noise_px = 0;             // the corner noise the prior is weighed against (> 0)
  cv::Size image_size;             // the images the prior is for (empty: any)
};

struct CalibrationOptions {
  LensModel lens_model = LensModel::kOpenCV5;
  bool fix_principal_point = false;  // keep cx, cy at their initial value (image centre if cold)
  bool fix_aspect_ratio = false;     // fy / fx held at its initial value
  bool zero_tangential = false;      // p1 = p2 = 0, fixed
  bool zero_distortion = false;      // every distortion coefficient 0, fixed
  std::vector<std::string> fixed;    // further parameters held fixed, by name ("k3", "fy", ...)
  // Parameters held at their starting value (0 when cold) when the views do not determine them,
  // instead of failing: on a rank deficiency whose weakest direction one of these dominates, it
  // is held and the bundle adjustment run again (CalibrationResult::held names each). E.g. the
  // rational coefficients k4..k6 of a lens with little distortion, where d/dk4 = -d/dk1.
  std::vector<std::string> hold_if_undetermined;
  int max_iterations = 100;          // Levenberg-Marquardt iterations
  double function_tolerance = 1e-12;
  double parameter_tolerance = 1e-12;
  // Bound on the relative standard deviation of fx and fy (unit-noise covariance scaled by the
  // residual variance) above which the solution is rejected as degenerate: e.g. every view
  // fronto-parallel, where the focal length cannot be told from the distance (paper §3.1).
  double max_relative_focal_std = 0.2;
  // With a prior, one frame suffices: it is the extra term of the cost above.
  std::optional<IntrinsicsPrior> prior;

  // Ceres style: true if usable, else false with the reason in *error.
  bool is_valid(std::string* error) const;
};

// Why the bundle adjustment stopped (ceres::Solver::Summary's termination type; a solver failure
// throws instead).
enum class SolverTermination {
  kConvergence,    // a function, gradient or parameter tolerance was reached
  kNoConvergence,  // the iteration limit was reached first
};
const char* solver_termination_name(SolverTermination t);  // "convergence", "no_convergence"

// The weak prior a held parameter is freed under where its uncertainty is needed (the expected
// error, the engine's scoring of the poses that could determine it): a standard deviation of 1
// in the coefficient's own unit, wide against the rational coefficients' effect at the rim.
inline constexpr double kHeldPriorStd = 1.0;

struct CalibrationResult {
  CameraModel model;
  std::vector<Pose> poses;  // T_cam_board per frame
  std::vector<bool> fixed;  // per intrinsic (those held below included)
  // The parameters of CalibrationOptions::hold_if_undetermined the views did not determine, in
  // the order they were held, with the reason (the rank deficiency that named each).
  std::vector<std::string> held;
  std::string held_reason;
  // With parameters held: the intrinsics' covariance (num_params() square, marginal over the
  // poses, zero rows for the fixed ones) with the held ones free under a prior of kHeldPriorStd
  // each, from the frames' information at the solution. Like `covariance` it is multiplied by
  // residual_variance to give the covariance at the measured noise; the prior is absolute (it
  // does not scale with the noise). A held value is a guess the keyframes did not confirm: the
  // expected error takes its uncertainty from here, so that a guess counts as unknown, not as
  // known. Empty when nothing is held.
  Eigen::MatrixXd held_covariance;
  int num_points = 0;
  int num_unknowns = 0;  // free intrinsics + 6 per frame
  int iterations = 0;
  SolverTermination termination = SolverTermination::kNoConvergence;
  std::string termination_message;  // Ceres' own words, e.g. which tolerance was reached
  bool solver_converged() const { return termination == SolverTermination::kConvergence; }
  double rms_px = 0;       // eps_res: sqrt(sum |p - pi(P)|^2 / N)
  std::vector<double> frame_rms_px;
  // Backward transport of covariance, Sigma_v = (J^T Sigma_p^-1 J)^+ with Sigma_p = I (paper
  // eq. 5). Order: intrinsics, then (r, t) per frame. Rows/columns of fixed parameters are 0.
  Eigen::MatrixXd covariance;
  // Residual variance sigma^2 = SSR / (2N - unknowns), an estimate of the point noise.
  double residual_variance = 0;
  std::vector<double> std_unit;    // sqrt(diag(covariance)) of the intrinsics (Sigma_p = I)
  std::vector<double> std_scaled;  // the same scaled by the residual variance: honest sigma
  std::vector<double> index_of_dispersion;  // sigma_unit^2 / |C| (sigma^2 where C = 0)
  int rank_deficiency = 0;  // eigenvalues of J^T J treated as zero by the pseudo-inverse
  double solve_ms = 0;

  Eigen::MatrixXd covariance_scaled() const { return covariance * residual_variance; }
  // Parameters are held and held_covariance is there (num_params() square).
  bool has_held_covariance() const {
    const Eigen::Index n = model.num_params();
    return !held.empty() && held_covariance.rows() == n && held_covariance.cols() == n;
  }
  Eigen::MatrixXd held_covariance_scaled() const { return held_covariance * residual_variance; }
};

// Warm start: a previous solution whose poses cover the first poses.size() frames. Frames beyond
// get their pose from PnP with the previous model.
struct WarmStart {
  CameraModel model;
  std::vector<Pose> poses;
};

// Calibrates from frames of correspondences. image_size is the sensor size in pixels.
// Throws Error(kInvalidArgument) for malformed input (NaN, < 4 points in a frame, ...) and
// Error(kDegenerate) when the data cannot determine the parameters (too few points, all views
// fronto-parallel, ...), naming the cause.
CalibrationResult calibrate(const std::vector<Observation>& frames, cv::Size image_size,
                            const CalibrationOptions& options = {},
                            const WarmStart* warm_start = nullptr);

// What options.prior alone says, as a result without frames (no poses, no points): the prior's
// mean, the covariance of the free intrinsics given the fixed ones (unit form, i.e. divided by
// noise_px^2, with residual_variance noise_px^2), and the figures derived from it. Pose
// selection chooses the first target with it. Error(kInvalidArgument) without a prior or for
// one the options reject.
CalibrationResult prior_result(cv::Size image_size, const CalibrationOptions& options);

}  // namespace posecal
