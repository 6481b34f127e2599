#include "io/result_file.hpp"

#include <cmath>

#include "calib/expected_error.hpp"

namespace posecal {

namespace {

// The leading n x n block of `m` (the intrinsics of a covariance ordered intrinsics, poses),
// row-major.
std::vector<double> row_major(const Eigen::MatrixXd& m, Eigen::Index n) {
  std::vector<double> v;
  v.reserve(static_cast<size_t>(n * n));
  for (Eigen::Index a = 0; a < n; ++a)
    for (Eigen::Index b = 0; b < n; ++b) v.push_back(m(a, b));
  return v;
}

Eigen::MatrixXd square(const std::vector<double>& v, Eigen::Index n) {
  Eigen::MatrixXd m(n, n);
  for (Eigen::Index a = 0; a < n; ++a)
    for (Eigen::Index b = 0; b < n; ++b) m(a, b) = v[static_cast<size_t>(a * n + b)];
  return m;
}

}  // namespace

void put_result_figures(const CalibrationResult& r, CalibrationFileExtras* extras) {
  const Eigen::Index n = r.model.num_params();
  extras->nr_of_frames = static_cast<int>(r.poses.size());
  extras->avg_reprojection_error = r.rms_px;
  extras->param_std = r.std_scaled;
  extras->covariance = row_major(r.covariance_scaled(), n);
  extras->held.clear();
  extras->held_covariance.clear();
  if (r.has_held_covariance()) {
    extras->held = r.held;
    extras->held_covariance = row_major(r.held_covariance_scaled(), n);
  }
  const double expected = expected_error(r).rms_px;
  extras->expected_error_px = std::isfinite(expected) ? expected : -1;
}

std::optional<CalibrationResult> result_figures_of(const ModelFile& file) {
  const Eigen::Index n = file.model.num_params();
  const size_t n2 = static_cast<size_t>(n * n);
  if (file.extras.covariance.size() != n2) return std::nullopt;
  CalibrationResult r;
  r.model = file.model;
  r.covariance = square(file.extras.covariance, n);
  r.fixed.assign(static_cast<size_t>(n), false);
  for (Eigen::Index a = 0; a < n; ++a) r.fixed[static_cast<size_t>(a)] = r.covariance(a, a) == 0;
  if (!file.extras.held.empty() && file.extras.held_covariance.size() == n2) {
    r.held = file.extras.held;
    r.held_covariance = square(file.extras.held_covariance, n);
  }
  r.residual_variance = 1;  // the file's covariances are already scaled
  return r;
}

}  // namespace posecal
