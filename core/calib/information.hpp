// The information maths of pose selection: the information about the intrinsics that one more
// view would add (paper §4.1 predicts the covariance after a candidate pose with it), quadrature
// over a board's corners, and the projection Gram matrix (docs/math.md, "Predicted covariance").
#pragma once

#include <Eigen/Core>
#include <vector>

#include "calib/calibration.hpp"
#include "lens/camera_model.hpp"
#include "lens/geometry.hpp"

namespace posecal {

// A square matrix over the intrinsics of any lens model, without heap allocation.
using IntrinsicsMatrix = Eigen::Matrix<double, Eigen::Dynamic, Eigen::Dynamic, 0, kMaxIntrinsics, kMaxIntrinsics>;

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

// The allocation-free core of frame_information(): the information of every intrinsic (fixed or
// not; *S is num_params() square), each point weighted if `weights` is given (one per point,
// >= 0), the pose as a rotation matrix. Returns false if the view does not determine the board
// pose (too few points in view); *S is then undefined.
bool frame_information_all(const CameraModel& model, const Eigen::Matrix3d& R_cam_board, const Eigen::Vector3d& t_cam_board,
                           const std::vector<cv::Point3d>& board_points, const double* weights, IntrinsicsMatrix* S);

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

// The positions of result.held among the model's parameters, in the order held. Throws
// Error(kInvalidArgument) naming a held name the model does not have.
std::vector<int> held_indices(const CalibrationResult& result);

// result.fixed with the held parameters opened: the intrinsics a result left free or held.
std::vector<bool> fixed_with_held_open(const CalibrationResult& result);

// Marginal information (Sigma_p = I) of the intrinsics a result left free or held: the sum of
// each frame's frame_information() at the solution (result.poses, one per frame of `frames`),
// plus `held_prior` on the held ones' diagonal (a weak prior that bounds the direction the frames
// leave undetermined). In the order of the false entries of *open, which it sets to result.fixed
// with the held parameters opened. aspect > 0: the calibration tied fy to aspect * fx (fy is
// fixed in result.fixed), and fy's information is folded onto fx. A prior of the calibration is
// not included. Throws Error(kInvalidArgument) if the frames do not match the result's poses.
Eigen::MatrixXd information_with_held(const CalibrationResult& result,
                                      const std::vector<Observation>& frames, double held_prior,
                                      std::vector<bool>* open, double aspect = 0);

// The indices of the intrinsics that are not fixed, in order.
std::vector<int> free_intrinsics(const std::vector<bool>& fixed);

// d(pixel)/d(free intrinsics) at `pixel`, the ray through it (unprojected with `model`) held
// fixed while the intrinsics move: how an error in the intrinsics moves that ray's projection.
// 2 x free_idx.size(); false if the pixel has no preimage.
bool ray_intrinsics_jacobian(const CameraModel& model, const std::vector<int>& free_idx, const Eigen::Vector2d& pixel,
                             Eigen::Matrix<double, 2, Eigen::Dynamic>* Jf);

// Mean of J^T J over a cols x rows grid of pixel centres, J = d(pixel)/d(free intrinsics) of the
// ray through each pixel (free parameters in the order of `fixed`'s false entries). For a
// covariance Sigma of the free intrinsics, trace(G Sigma) is the expected squared projection
// error averaged over the image, i.e. the expected eps_gt^2 (docs/math.md). Grid pixels
// without a preimage are left out; all zero if none has one.
Eigen::MatrixXd projection_gram(const CameraModel& model, const std::vector<bool>& fixed, int cols = 16,
                                int rows = 9);

}  // namespace posecal
