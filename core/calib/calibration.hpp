// Calibration: Zhang's initial solution (OpenCV) refined by a Ceres bundle adjustment over the
// intrinsics and every frame's board pose, with the parameter covariance of the paper's eq. 5.
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

struct CalibrationOptions {
  LensModel lens_model = LensModel::kOpenCV5;
  bool fix_principal_point = false;  // keep cx, cy at their initial value (image centre if cold)
  bool fix_aspect_ratio = false;     // fy / fx held at its initial value
  bool zero_tangential = false;      // p1 = p2 = 0, fixed
  bool zero_distortion = false;      // every distortion coefficient 0, fixed
  std::vector<std::string> fixed;    // further parameters held fixed, by name ("k3", "fy", ...)
  int max_iterations = 100;          // Levenberg-Marquardt iterations
  double function_tolerance = 1e-12;
  double parameter_tolerance = 1e-12;
  // Bound on the relative standard deviation of fx and fy (unit-noise covariance scaled by the
  // residual variance) above which the solution is rejected as degenerate: e.g. every view
  // fronto-parallel, where the focal length cannot be told from the distance (paper §3.1).
  double max_relative_focal_std = 0.2;

  // Ceres style: true if usable, else false with the reason in *error.
  bool is_valid(std::string* error) const;
};

struct CalibrationResult {
  CameraModel model;
  std::vector<Pose> poses;  // T_cam_board per frame
  std::vector<bool> fixed;  // per intrinsic
  int num_points = 0;
  int num_unknowns = 0;  // free intrinsics + 6 per frame
  int iterations = 0;
  bool converged = false;  // solver reached a tolerance (not the iteration cap)
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

// Information about the intrinsics (J^T J with Sigma_p = I, free parameters only, in the order
// of `fixed`'s false entries) that observing `board_points` at T_cam_board would add: the Schur
// complement of one frame's normal equations onto the intrinsics. Adding it to the inverse of
// the current intrinsics covariance predicts the covariance after that frame, exactly at the
// linearisation point.
Eigen::MatrixXd frame_information(const CameraModel& model, const Pose& T_cam_board,
                                  const std::vector<cv::Point3d>& board_points,
                                  const std::vector<bool>& fixed);

// As above with each point's contribution scaled by its weight (one per point): with the points
// of corner_quadrature(), a cheap approximation of a whole board's information.
Eigen::MatrixXd frame_information(const CameraModel& model, const Pose& T_cam_board,
                                  const std::vector<cv::Point3d>& board_points,
                                  const std::vector<double>& weights, const std::vector<bool>& fixed);

// The allocation-free core of frame_information() for models with at most 9 intrinsics: the
// information of all of them (fixed or not; rows and columns past num_params() are zero), each
// point weighted if `weights` is given (one per point, >= 0), the pose as a rotation matrix.
// Returns false if the view does not determine the board pose (too few points in view); *S is
// then undefined.
bool frame_information_all9(const CameraModel& model, const Eigen::Matrix3d& R_cam_board, const Eigen::Vector3d& t_cam_board,
                            const std::vector<cv::Point3d>& board_points, const double* weights,
                            Eigen::Matrix<double, 9, 9>* S);

// A few weighted points standing in for a planar grid of corners in sums over the corners (as in
// frame_information): along the board's x and y axes the nodes_x- and nodes_y-point Gauss rules
// of the grid's coordinates (2 or 3 nodes; n nodes sum polynomials of degree up to 2n - 1 in that
// coordinate exactly), their product, weights summing to the corner count. Returns the corners
// themselves with weight 1 if they are not a full, regular, planar grid with more values per
// axis than nodes. Throws Error(kInvalidArgument) for other node counts.
void corner_quadrature(const std::vector<cv::Point3d>& corners, int nodes_x, int nodes_y, std::vector<cv::Point3d>* points,
                       std::vector<double>* weights);

// Marginal information of the free intrinsics from a result: inverse of their covariance block.
Eigen::MatrixXd intrinsics_information(const CalibrationResult& result);

// Mean of J^T J over a cols x rows grid of pixel centres, J = d(pixel)/d(free intrinsics) of the
// ray through each pixel (free parameters in the order of `fixed`'s false entries). For a
// covariance Sigma of the free intrinsics, trace(G Sigma) is the expected squared projection
// error averaged over the image, i.e. the expected eps_gt^2 (docs/math.md). Grid pixels
// without a preimage are left out; all zero if none has one.
Eigen::MatrixXd projection_gram(const CameraModel& model, const std::vector<bool>& fixed, int cols = 16,
                                int rows = 9);

// Fits the pose of one frame with fixed intrinsics (PnP, then Ceres refinement). Returns false if
// the frame has fewer than 4 points or the fit fails.
bool estimate_pose(const CameraModel& model, const Observation& frame, Pose* T_cam_board,
                   double* rms_px = nullptr);

}  // namespace posecal
