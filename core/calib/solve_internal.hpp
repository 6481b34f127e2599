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

// Residual statistics, the covariance of eq. 5 and the degeneracy checks at the solution, into
// *res (whose model is set). Throws Error(kDegenerate) naming the parameter the views cannot
// determine.
void covariance_at_solution(ceres::Problem& problem, Solution& solution, const CovarianceInput& in,
                            CalibrationResult* res);

}  // namespace posecal::calib_internal
