#include "calib/expected_error.hpp"

#include <algorithm>
#include <cmath>
#include <random>
#include <vector>

#include <Eigen/Eigenvalues>
#include <limits>

#include "calib/information.hpp"
#include "common/error.hpp"

namespace posecal {

namespace {

void check_grid(const CalibrationResult& r, int cols, int rows) {
  if (cols < 2 || rows < 2)
    throw Error(ErrorCode::kInvalidArgument, "expected error: the grid must be at least 2x2");
  const Eigen::Index n = r.model.num_params();
  if (r.covariance.rows() < n || r.covariance.cols() < n ||
      static_cast<Eigen::Index>(r.fixed.size()) != n) {
    throw Error(ErrorCode::kInvalidArgument,
                "expected error: the result has no covariance of its intrinsics");
  }
}

// The intrinsics the figure is over, and their covariance at unit noise: the free ones, and with
// parameters held the held ones too, under their weak prior (CalibrationResult::held_covariance).
struct Uncertain {
  std::vector<int> idx;
  Eigen::MatrixXd C;
};

Uncertain uncertain_intrinsics(const CalibrationResult& r) {
  const bool with_held = r.has_held_covariance();
  Uncertain u{free_intrinsics(with_held ? fixed_with_held_open(r) : r.fixed), {}};
  const Eigen::MatrixXd& cov = with_held ? r.held_covariance : r.covariance;
  const Eigen::Index m = static_cast<Eigen::Index>(u.idx.size());
  u.C.resize(m, m);
  for (Eigen::Index a = 0; a < m; ++a)
    for (Eigen::Index b = 0; b < m; ++b) u.C(a, b) = cov(u.idx[a], u.idx[b]);
  return u;
}

// Pixel of grid point (i, j), edge to edge.
Eigen::Vector2d grid_pixel(const CameraModel& m, int i, int j, int cols, int rows) {
  return {i * (m.width() - 1.0) / (cols - 1), j * (m.height() - 1.0) / (rows - 1)};
}

// Mean and 90th percentile of the mean over the grid of |J_p e|, e ~ N(0, C): `jacobians` stacks
// the points' 2 x m Jacobians (2P x m).
void distance_distribution(const Eigen::MatrixXd& jacobians, const Eigen::MatrixXd& C, ExpectedError* out) {
  const Eigen::Index m = C.rows();
  const Eigen::Index points = jacobians.rows() / 2;
  // C = V D V^T; e = V sqrt(D) z with z ~ N(0, I) (eigenvalues below 0, numerical, are 0).
  const Eigen::SelfAdjointEigenSolver<Eigen::MatrixXd> eig(C);
  const Eigen::MatrixXd L = eig.eigenvectors() * eig.eigenvalues().cwiseMax(0.0).cwiseSqrt().asDiagonal();
  const Eigen::MatrixXd A = jacobians * L;  // 2P x m
  std::mt19937_64 rng(0x5eedull);
  std::normal_distribution<double> normal;
  constexpr int kChunk = 250;
  std::vector<double> means;
  means.reserve(kExpectedErrorDraws);
  Eigen::MatrixXd Z(m, kChunk);
  for (int done = 0; done < kExpectedErrorDraws; done += kChunk) {
    for (Eigen::Index c = 0; c < kChunk; ++c)
      for (Eigen::Index r = 0; r < m; ++r) Z(r, c) = normal(rng);
    const Eigen::MatrixXd E = A * Z;  // 2P x kChunk: every point's error for every draw
    for (Eigen::Index d = 0; d < kChunk; ++d) {
      double sum = 0;
      for (Eigen::Index p = 0; p < points; ++p) sum += std::hypot(E(2 * p, d), E(2 * p + 1, d));
      means.push_back(sum / static_cast<double>(points));
    }
  }
  double total = 0;
  for (double v : means) total += v;
  out->mean_px = total / static_cast<double>(means.size());
  std::sort(means.begin(), means.end());
  const double at = 0.9 * static_cast<double>(means.size() - 1);
  const size_t lo = static_cast<size_t>(at);
  const size_t hi = std::min(lo + 1, means.size() - 1);
  out->p90_px = means[lo] + (means[hi] - means[lo]) * (at - static_cast<double>(lo));
}

}  // namespace

ExpectedError expected_error(const CalibrationResult& result, int cols, int rows) {
  check_grid(result, cols, rows);
  const CameraModel& model = result.model;
  const Uncertain u = uncertain_intrinsics(result);
  const std::vector<int>& free_idx = u.idx;
  const Eigen::MatrixXd& C = u.C;
  const Eigen::Index m = static_cast<Eigen::Index>(free_idx.size());
  Eigen::MatrixXd G = Eigen::MatrixXd::Zero(m, m);  // mean of J^T J over the grid
  Eigen::Matrix<double, 2, Eigen::Dynamic> J(2, m);
  Eigen::MatrixXd jacobians(2 * cols * rows, m);
  ExpectedError out;
  out.grid_points = cols * rows;
  for (int j = 0; j < rows; ++j) {
    for (int i = 0; i < cols; ++i) {
      if (!ray_intrinsics_jacobian(model, free_idx, grid_pixel(model, i, j, cols, rows), &J))
        continue;
      G.noalias() += J.transpose() * J;
      jacobians.middleRows(2 * out.points, 2) = J;
      ++out.points;
    }
  }
  if (out.points == 0) {
    out.rms_px = out.rms_unit_px = out.mean_px = out.p90_px = std::numeric_limits<double>::quiet_NaN();
    return out;
  }
  G /= out.points;
  const double ms_unit = std::max(0.0, (G * C).trace());
  out.rms_unit_px = std::sqrt(ms_unit);
  const double noise_variance = std::max(0.0, result.residual_variance);
  out.rms_px = out.rms_unit_px * std::sqrt(noise_variance);
  distance_distribution(jacobians.topRows(2 * out.points), C * noise_variance, &out);
  // Knowing intrinsic k exactly conditions the covariance to C - C_k C_k^T / C_kk, which lowers
  // trace(G C) by C_k^T G C_k / C_kk.
  for (Eigen::Index k = 0; k < m; ++k) {
    if (!(C(k, k) > 0) || !(ms_unit > 0)) continue;
    const double share = C.col(k).dot(G * C.col(k)) / C(k, k) / ms_unit;
    if (out.limiting_param < 0 || share > out.limiting_share) {
      out.limiting_param = free_idx[k];
      out.limiting_share = std::min(1.0, std::max(0.0, share));
    }
  }
  return out;
}

int grid_points_with_ray(const CameraModel& model, int cols, int rows) {
  if (cols < 2 || rows < 2)
    throw Error(ErrorCode::kInvalidArgument, "grid_points_with_ray: the grid must be at least 2x2");
  int points = 0;
  Eigen::Vector3d ray;
  for (int j = 0; j < rows; ++j)
    for (int i = 0; i < cols; ++i)
      points += model.unproject_ray(grid_pixel(model, i, j, cols, rows), &ray);
  return points;
}

cv::Mat expected_error_map(const CalibrationResult& result, int cols, int rows) {
  check_grid(result, cols, rows);
  const CameraModel& model = result.model;
  const Uncertain u = uncertain_intrinsics(result);
  const std::vector<int>& free_idx = u.idx;
  const Eigen::MatrixXd C = u.C * std::max(0.0, result.residual_variance);
  Eigen::Matrix<double, 2, Eigen::Dynamic> J(2, static_cast<Eigen::Index>(free_idx.size()));
  Eigen::Matrix<double, 2, Eigen::Dynamic> JC(2, static_cast<Eigen::Index>(free_idx.size()));
  cv::Mat map(rows, cols, CV_32F);
  for (int j = 0; j < rows; ++j) {
    float* row = map.ptr<float>(j);
    for (int i = 0; i < cols; ++i) {
      if (!ray_intrinsics_jacobian(model, free_idx, grid_pixel(model, i, j, cols, rows), &J)) {
        row[i] = std::numeric_limits<float>::quiet_NaN();
        continue;
      }
      JC.noalias() = J * C;  // trace(J C J^T) without temporaries
      row[i] = static_cast<float>(std::sqrt(std::max(0.0, JC.cwiseProduct(J).sum())));
    }
  }
  return map;
}

}  // namespace posecal
