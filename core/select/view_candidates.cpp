#include "select/view_candidates.hpp"

#include <algorithm>
#include <cmath>

#include <Eigen/Cholesky>

#include "calib/information.hpp"
#include "common/error.hpp"

namespace posecal {

CovariancePrediction predict_covariance(const Eigen::MatrixXd& information, const Eigen::MatrixXd& gram,
                                        const Eigen::MatrixXd& frame_info) {
  const Eigen::MatrixXd info = information + frame_info;
  const Eigen::MatrixXd cov = info.ldlt().solve(Eigen::MatrixXd::Identity(info.rows(), info.cols()));
  CovariancePrediction p;
  p.variance = cov.diagonal();
  if (gram.size()) p.projection = gram.cwiseProduct(cov).sum();  // trace(G Sigma), both symmetric
  return p;
}

namespace {

// Variances and trace(G info^-1) of a positive definite N x N information matrix by a plain
// Cholesky factorisation, info = L L^T, and L^-1: cov = L^-T L^-1, trace(G cov) = sum of the
// rows l_k of L^-1 of l_k G l_k^T. False (nothing written) if info is not numerically positive
// definite; the caller falls back to LDLT.
template <int N>
bool predict_cholesky(const Eigen::Matrix<double, N, N>& info, const Eigen::Matrix<double, N, N>* G,
                      CovariancePrediction* p) {
  double L[N][N] = {}, Li[N][N] = {};
  for (int j = 0; j < N; ++j) {
    double d = info(j, j);
    for (int k = 0; k < j; ++k) d -= L[j][k] * L[j][k];
    if (!(d > 1e-300 * std::max(1.0, std::abs(info(j, j))))) return false;
    const double ljj = std::sqrt(d);
    L[j][j] = ljj;
    for (int i = j + 1; i < N; ++i) {
      double v = info(i, j);
      for (int k = 0; k < j; ++k) v -= L[i][k] * L[j][k];
      L[i][j] = v / ljj;
    }
  }
  for (int i = 0; i < N; ++i) {  // L^-1, lower triangular, row by row
    Li[i][i] = 1.0 / L[i][i];
    for (int j = 0; j < i; ++j) {
      double v = 0;
      for (int k = j; k < i; ++k) v -= L[i][k] * Li[k][j];
      Li[i][j] = v / L[i][i];
    }
  }
  p->variance.resize(N);
  for (int c = 0; c < N; ++c) {
    double v = 0;
    for (int k = c; k < N; ++k) v += Li[k][c] * Li[k][c];
    p->variance(c) = v;
  }
  p->projection = 0;
  if (G) {
    double tr = 0;
    for (int k = 0; k < N; ++k) {
      for (int a = 0; a <= k; ++a) {
        double ga = 0;
        for (int b = 0; b <= k; ++b) ga += (*G)(a, b) * Li[k][b];
        tr += Li[k][a] * ga;
      }
    }
    p->projection = tr;
  }
  return std::isfinite(p->projection) && p->variance.allFinite();
}

}  // namespace

template <int N>
CovariancePrediction ViewCandidates::predict_fixed(const Eigen::Matrix3d& R, const Eigen::Vector3d& t,
                                                   const std::vector<cv::Point3d>& points,
                                                   const std::vector<double>* weights) const {
  const int m = static_cast<int>(information_.rows());
  IntrinsicsMatrix S;
  const bool seen = frame_information_all(estimate_, R, t, points, weights ? weights->data() : nullptr, &S);
  CovariancePrediction p;
  if (m == N) {  // every intrinsic free: fixed sizes throughout
    using Full = Eigen::Matrix<double, N, N>;
    Full info = information_;
    if (seen) info += S;
    const Full G = gram_.size() ? Full(gram_) : Full::Zero();
    if (predict_cholesky<N>(info, gram_.size() ? &G : nullptr, &p)) return p;
    const Full cov = info.ldlt().solve(Full::Identity());
    p.variance = cov.diagonal();
    if (gram_.size()) p.projection = G.cwiseProduct(cov).sum();
    return p;
  }
  using Small = Eigen::Matrix<double, Eigen::Dynamic, Eigen::Dynamic, 0, N, N>;  // no heap allocation
  Small info = information_;
  if (seen) {
    for (int a = 0; a < m; ++a)
      for (int b = 0; b < m; ++b) info(a, b) += S(free_[a], free_[b]);
  }
  const Small cov = info.ldlt().solve(Small::Identity(m, m));
  p.variance = cov.diagonal();
  if (gram_.size()) p.projection = gram_.cwiseProduct(cov).sum();
  return p;
}

CovariancePrediction ViewCandidates::predict(const Eigen::Matrix3d& R, const Eigen::Vector3d& t,
                                             const std::vector<cv::Point3d>& points,
                                             const std::vector<double>* weights) const {
  return with_lens_model(estimate_.lens_model(),
                         [&](auto lm) { return predict_fixed<kNumParamsOf<decltype(lm)>>(R, t, points, weights); });
}

ViewCandidates::ViewCandidates(const CameraModel& estimate, const Board& board, const std::vector<bool>& fixed,
                               const Eigen::MatrixXd& information, const Eigen::MatrixXd& gram,
                               const std::vector<ViewPose>& views, const ViewCandidateOptions& options)
    : estimate_(estimate), board_(board), fixed_(fixed), information_(information), gram_(gram), options_(options) {
  const long free = std::count(fixed.begin(), fixed.end(), false);
  if (static_cast<int>(fixed.size()) != estimate.num_params() || information.rows() != free ||
      information.cols() != free || (gram.size() && (gram.rows() != free || gram.cols() != free))) {
    throw Error(ErrorCode::kInvalidArgument, "view candidates: information, Gram matrix and fixed flags disagree in size");
  }
  if (options.count < 0 || options.shortlist < 1 || !(options.margin_px >= 0)) {
    throw Error(ErrorCode::kInvalidArgument, "view candidates: count >= 0, shortlist >= 1 and margin >= 0");
  }
  for (int i = 0; i < estimate.num_params(); ++i)
    if (!fixed[i]) free_.push_back(i);
  std::vector<cv::Point3d> qp;
  std::vector<double> qw;
  corner_quadrature(board.corners(), 3, 3, &qp, &qw);
  const std::vector<cv::Point3d> outline = board.outline();
  views_.reserve(std::min(views.size(), static_cast<size_t>(options.count)));
  for (const ViewPose& p : views) {
    if (static_cast<int>(views_.size()) >= options.count) break;
    if (!board_outline_in_view(estimate, outline, p.R, p.t, options.margin_px)) continue;
    View v;
    v.R = p.R;
    v.t = p.t;
    v.screened = predict(v.R, v.t, qp, &qw);
    views_.push_back(std::move(v));
  }
}

std::vector<size_t> ViewCandidates::best(int rank_by) const {
  std::vector<size_t> idx(views_.size());
  for (size_t i = 0; i < idx.size(); ++i) idx[i] = i;
  auto key = [&](size_t i) { return rank_by < 0 ? views_[i].screened.projection : views_[i].screened.variance(rank_by); };
  const size_t n = std::min(static_cast<size_t>(options_.shortlist), idx.size());
  std::partial_sort(idx.begin(), idx.begin() + static_cast<long>(n), idx.end(), [&](size_t a, size_t b) {
    const double ka = key(a), kb = key(b);
    return ka < kb || (ka == kb && a < b);
  });
  idx.resize(n);
  return idx;
}

std::vector<ViewCandidates::Exact> ViewCandidates::shortlist(int rank_by, int also_by) {
  const int free = static_cast<int>(information_.rows());
  if (rank_by >= free || also_by >= free) throw Error(ErrorCode::kInvalidArgument, "view candidates: no such free intrinsic");
  if (rank_by < 0 && !gram_.size()) throw Error(ErrorCode::kInvalidArgument, "view candidates: ranking by projection needs a Gram matrix");
  std::vector<size_t> idx = best(rank_by);
  if (also_by >= 0) {
    for (size_t i : best(also_by))
      if (std::find(idx.begin(), idx.end(), i) == idx.end()) idx.push_back(i);
  }
  const double margin = options_.margin_px;
  std::vector<Exact> out;
  for (size_t i : idx) {
    View& v = views_[i];
    if (!v.exact_done) {
      v.exact_done = true;
      v.target.T_cam_board = Pose::from_rotation(v.R, v.t);
      v.target.kind = TargetKind::kView;
      v.visible = board_fully_visible(estimate_, board_, v.target.T_cam_board, margin);
      if (v.visible) v.exact = predict(v.R, v.t, board_.corners(), nullptr);
    }
    if (v.visible) out.push_back({&v.target, v.exact});
  }
  return out;
}

}  // namespace posecal
