// Internal to calib/: the parts of calibrate() shared by the bundle adjustment (solve.cpp) and the
// covariance (covariance.cpp).
#pragma once

#include <ceres/ceres.h>

#include <array>
#include <string>
#include <vector>

#include "calib/calibration.hpp"

namespace posecal::calib_internal {

// The bundle adjustment's parameter blocks at the solution: the intrinsics, then each frame's
// rotation vector and translation.
struct Solution {
  std::vector<double> intrinsics;
  std::vector<std::array<double, 6>> rt;
  std::vector<double*> blocks() {
    std::vector<double*> b{intrinsics.data()};
    for (auto& r : rt) b.push_back(r.data());
    return b;
  }
};

// What the covariance needs to know of the problem.
struct CovarianceInput {
  const std::vector<Observation>* frames = nullptr;
  std::vector<bool> fixed;  // per intrinsic
  double aspect = 0;        // > 0: fy = aspect * fx
  int num_points = 0;
  int num_unknowns = 0;
  const std::vector<std::string>* names = nullptr;
  double max_relative_focal_std = 0;
  int prior_rows = 0;  // the prior's rows on free parameters, after the points' (IntrinsicsPrior)
};

// The views leave a direction of the intrinsics undetermined (a rank deficiency); `direction`
// holds its component on each intrinsic (0 for fixed ones; Jacobi-scaled, so comparable).
// calibrate() holds the parameter of CalibrationOptions::hold_if_undetermined with the largest
// component, else passes the error on.
class Undetermined : public Error {
 public:
  Undetermined(const std::string& message, std::vector<double> direction)
      : Error(ErrorCode::kDegenerate, message), direction_(std::move(direction)) {}
  const std::vector<double>& direction() const { return direction_; }

 private:
  std::vector<double> direction_;
};

// The views do not pin a focal length down (relative std above
// CalibrationOptions::max_relative_focal_std). calibrate() then holds every parameter of
// hold_if_undetermined not yet held (a tilted sensor's tau trades with the focal length on two
// views) and solves again, else passes the error on.
class FocalUnobservable : public Error {
 public:
  explicit FocalUnobservable(const std::string& message) : Error(ErrorCode::kDegenerate, message) {}
};

// Residual statistics, the covariance of eq. 5 and the degeneracy checks at the solution, into
// *res (whose model is set). Throws Undetermined for a rank deficiency, FocalUnobservable,
// Error(kDegenerate) for another degeneracy, each naming the parameter the views cannot determine.
void covariance_at_solution(ceres::Problem& problem, Solution& solution, const CovarianceInput& in,
                            CalibrationResult* res);

// fy = aspect * fx (CalibrationOptions::fix_aspect_ratio; fy is not a parameter of the
// adjustment): fy's row and column of a covariance in the ambient order (fx first, fy second)
// follow fx's.
void tie_fy_to_fx(double aspect, Eigen::MatrixXd* cov);

}  // namespace posecal::calib_internal
