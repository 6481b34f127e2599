// The information maths of pose selection (docs/math.md, "Predicted covariance"): what one more
// view of the board would tell about the intrinsics, quadrature over a board's corners, and the
// Gram matrix that turns a covariance into the expected projection error over the image.
#include "calib/information.hpp"

#include <ceres/jet.h>

#include <Eigen/Dense>
#include <algorithm>
#include <cmath>
#include <set>

#include "common/error.hpp"

namespace posecal {

namespace {

// frame_information() for lens model M. The pose enters through a left perturbation of the board
// points in the camera frame, d(p_cam) = [-[R P]x | I] (dw, dt): the Schur complement onto the
// intrinsics does not depend on how the eliminated pose is parametrised, so this equals the
// complement for the rotation vector, without differentiating the rotation; the projection's
// derivatives are the model's own (M::project_jacobians). `weights` (optional, one per point)
// scales each point's contribution. Returns false (S untouched) if the pose is unobservable from
// the points in view.
template <class M>
[[gnu::always_inline]] inline bool frame_information_full(const CameraModel& model, const Eigen::Matrix3d& R,
                                                          const Eigen::Vector3d& t,
                                                          const std::vector<cv::Point3d>& board_points,
                                                          const double* weights,
                                                          Eigen::Matrix<double, kNumParamsOf<M>, kNumParamsOf<M>>* S) {
  constexpr int kN = kNumParamsOf<M>;  // intrinsics
  constexpr int kT = kN + 6;           // and the pose
  using MatA = Eigen::Matrix<double, kN, kN>;
  using MatB = Eigen::Matrix<double, kN, 6>;
  MatA A = MatA::Zero();
  MatB B = MatB::Zero();
  Eigen::Matrix<double, 6, 6> D = Eigen::Matrix<double, 6, 6>::Zero();
  Eigen::Matrix<double, 2, kN> Ji = Eigen::Matrix<double, 2, kN>::Zero();
  Eigen::Matrix<double, 2, 3> Jc;
  Eigen::Matrix<double, 3, 6> dpc = Eigen::Matrix<double, 3, 6>::Zero();
  dpc.template rightCols<3>().setIdentity();
  double Msum[kT][kT] = {};  // [A B; B^T D], upper triangle
  // A ray model sees directions up to its fold (beyond 90 degrees for a fisheye), the others
  // the half-space in front of the camera.
  [[maybe_unused]] double max_theta = 0;
  if constexpr (M::kRayModel) max_theta = M::max_theta(model.params().data() + kNumPinholeParams);
  for (size_t p = 0; p < board_points.size(); ++p) {
    const cv::Point3d& P = board_points[p];
    const Eigen::Vector3d RP = R * Eigen::Vector3d(P.x, P.y, P.z);
    const Eigen::Vector3d pc = RP + t;
    if constexpr (M::kRayModel) {
      if (!(pc.squaredNorm() > 1e-18) || !(std::atan2(pc.head<2>().norm(), pc.z()) < max_theta))
        continue;
    } else {
      if (!(pc.z() > 1e-9)) continue;
    }
    double u, v;
    M::project_jacobians(model.params().data(), pc, &u, &v, &Jc, Ji.data());
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
    // [Ji | Jp] into the upper triangle of a kT x kT sum: symmetric, half the work (Eigen would
    // call its GEMM kernel for these sizes, several times slower here).
    double J0[kT], J1[kT];
    for (int k = 0; k < kN; ++k) J0[k] = Ji(0, k), J1[k] = Ji(1, k);
    for (int k = 0; k < 6; ++k) J0[kN + k] = Jp(0, k), J1[kN + k] = Jp(1, k);
    for (int a = 0; a < kT; ++a)
      for (int b = a; b < kT; ++b) Msum[a][b] += J0[a] * J0[b] + J1[a] * J1[b];
  }
  for (int a = 0; a < kT; ++a) {
    for (int b = a; b < kT; ++b) {
      if (b < kN) {
        A(a, b) = A(b, a) = Msum[a][b];
      } else if (a < kN) {
        B(a, b - kN) = Msum[a][b];
      } else {
        D(a - kN, b - kN) = D(b - kN, a - kN) = Msum[a][b];
      }
    }
  }
  if (!(D.trace() > 0)) return false;
  // S = A - B D^-1 B^T, by D = L L^T and X = L^-1 B^T: S = A - X^T X.
  const Eigen::LLT<Eigen::Matrix<double, 6, 6>> llt(D);
  if (llt.info() == Eigen::Success) {
    const Eigen::Matrix<double, 6, kN> X = llt.matrixL().solve(B.transpose());
    *S = A - X.transpose().lazyProduct(X);
    return true;
  }
  const Eigen::LDLT<Eigen::Matrix<double, 6, 6>> ldlt(D);  // semi-definite: few points in view
  if (ldlt.info() != Eigen::Success) return false;
  const MatB BDinv = ldlt.solve(B.transpose()).transpose();
  *S = A - BDinv.lazyProduct(B.transpose());
  return true;
}

// Each model's instance, compiled twice: for x86-64-v3 CPUs (AVX2, FMA; chosen at load time where
// available: the accumulation over points is most of the cost of screening view candidates) and
// for the baseline. Not under ThreadSanitizer: it instruments the clones' resolver, which the
// dynamic loader runs before TSan has started (every program crashed at load time).
#if defined(__SANITIZE_THREAD__)
#define POSECAL_INFORMATION_TARGETS
#elif defined(__has_feature)
#if __has_feature(thread_sanitizer)
#define POSECAL_INFORMATION_TARGETS
#endif
#endif
#ifndef POSECAL_INFORMATION_TARGETS
#define POSECAL_INFORMATION_TARGETS __attribute__((target_clones("arch=x86-64-v3", "default")))
#endif
#define POSECAL_INFORMATION_CLONE(Model)                                                                     \
  POSECAL_INFORMATION_TARGETS bool frame_information_of(                                                     \
      lens::Model, const CameraModel& model, const Eigen::Matrix3d& R, const Eigen::Vector3d& t,             \
      const std::vector<cv::Point3d>& board_points, const double* weights,                                   \
      Eigen::Matrix<double, kNumParamsOf<lens::Model>, kNumParamsOf<lens::Model>>* S) {                      \
    return frame_information_full<lens::Model>(model, R, t, board_points, weights, S);                       \
  }
POSECAL_LENS_MODELS(POSECAL_INFORMATION_CLONE)
#undef POSECAL_INFORMATION_CLONE
#undef POSECAL_INFORMATION_TARGETS

// The information of every intrinsic into *S (num_params() square); false if the view does not
// determine the board pose.
bool information_all(const CameraModel& model, const Eigen::Matrix3d& R, const Eigen::Vector3d& t,
                     const std::vector<cv::Point3d>& board_points, const double* weights, IntrinsicsMatrix* S) {
  return with_lens_model(model.lens_model(), [&](auto lm) {
    constexpr int kN = kNumParamsOf<decltype(lm)>;
    Eigen::Matrix<double, kN, kN> Sm;
    if (!frame_information_of(lm, model, R, t, board_points, weights, &Sm)) return false;
    *S = Sm;
    return true;
  });
}

// The free rows and columns of the information of every intrinsic.
Eigen::MatrixXd free_block(const CameraModel& model, const Pose& T_cam_board, const std::vector<cv::Point3d>& board_points,
                           const double* weights, const std::vector<bool>& fixed) {
  std::vector<int> free_idx;
  for (int i = 0; i < model.num_params(); ++i)
    if (!fixed[i]) free_idx.push_back(i);
  const int m = static_cast<int>(free_idx.size());
  IntrinsicsMatrix S;
  if (!information_all(model, T_cam_board.R(), T_cam_board.t, board_points, weights, &S)) {
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
  if (static_cast<int>(fixed.size()) != model.num_params()) {
    throw Error(ErrorCode::kInvalidArgument, "frame_information: fixed size");
  }
  return free_block(model, T_cam_board, board_points, nullptr, fixed);
}

Eigen::MatrixXd frame_information(const CameraModel& model, const Pose& T_cam_board,
                                  const std::vector<cv::Point3d>& board_points,
                                  const std::vector<double>& weights, const std::vector<bool>& fixed) {
  if (static_cast<int>(fixed.size()) != model.num_params()) {
    throw Error(ErrorCode::kInvalidArgument, "frame_information: fixed size");
  }
  if (weights.size() != board_points.size()) throw Error(ErrorCode::kInvalidArgument, "frame_information: one weight per point");
  for (double w : weights)
    if (!(w >= 0 && std::isfinite(w))) throw Error(ErrorCode::kInvalidArgument, "frame_information: weights must be finite and >= 0");
  return free_block(model, T_cam_board, board_points, weights.data(), fixed);
}

bool frame_information_all(const CameraModel& model, const Eigen::Matrix3d& R_cam_board, const Eigen::Vector3d& t_cam_board,
                           const std::vector<cv::Point3d>& board_points, const double* weights, IntrinsicsMatrix* S) {
  return information_all(model, R_cam_board, t_cam_board, board_points, weights, S);
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

std::vector<int> held_indices(const CalibrationResult& result) {
  const std::vector<std::string>& names = result.model.param_names();
  std::vector<int> idx;
  for (const std::string& h : result.held) {
    const auto it = std::find(names.begin(), names.end(), h);
    if (it == names.end())
      throw Error(ErrorCode::kInvalidArgument, "unknown held parameter '" + h + "' of " +
                                                   lens_model_name(result.model.lens_model()));
    idx.push_back(static_cast<int>(it - names.begin()));
  }
  return idx;
}

std::vector<bool> fixed_with_held_open(const CalibrationResult& result) {
  std::vector<bool> open = result.fixed;
  for (int h : held_indices(result)) open.at(static_cast<size_t>(h)) = false;
  return open;
}

Eigen::MatrixXd information_with_held(const CalibrationResult& result,
                                      const std::vector<Observation>& frames, double held_prior,
                                      std::vector<bool>* open, double aspect) {
  if (frames.size() != result.poses.size())
    throw Error(ErrorCode::kInvalidArgument,
                "information_with_held: one frame per pose of the result");
  const std::vector<int> held_idx = held_indices(result);
  *open = result.fixed;
  for (int h : held_idx) (*open)[static_cast<size_t>(h)] = false;
  // With a tied fy, the information over (fx, fy, ...) first, then x = T x' with fy = aspect fx.
  const bool tied = aspect > 0 && !(*open)[0] && (*open)[1];
  std::vector<bool> with_fy = *open;
  if (tied) with_fy[1] = false;
  const int m = static_cast<int>(std::count(with_fy.begin(), with_fy.end(), false));
  Eigen::MatrixXd info = Eigen::MatrixXd::Zero(m, m);
  for (size_t k = 0; k < frames.size(); ++k)
    info += frame_information(result.model, result.poses[k], frames[k].board_points, with_fy);
  for (int h : held_idx) {
    const int k = static_cast<int>(std::count(with_fy.begin(), with_fy.begin() + h, false));
    info(k, k) += held_prior;
  }
  if (!tied) return info;
  Eigen::MatrixXd T = Eigen::MatrixXd::Zero(m, m - 1);
  for (int a = 0, b = 0; a < m; ++a) {
    if (a == 1) {
      T(1, 0) = aspect;  // fx is free and first, fy second
      continue;
    }
    T(a, b++) = 1;
  }
  return T.transpose() * info * T;
}

std::vector<int> free_intrinsics(const std::vector<bool>& fixed) {
  std::vector<int> free_idx;
  for (size_t i = 0; i < fixed.size(); ++i)
    if (!fixed[i]) free_idx.push_back(static_cast<int>(i));
  return free_idx;
}

bool ray_intrinsics_jacobian(const CameraModel& model, const std::vector<int>& free_idx, const Eigen::Vector2d& pixel,
                             Eigen::Matrix<double, 2, Eigen::Dynamic>* Jf) {
  // The pixel's unit ray: the whole field of view (beyond 90 degrees for a fisheye); a pinhole
  // model's intrinsic Jacobian does not depend on the point's distance along the ray.
  Eigen::Vector3d ray;
  Eigen::Vector2d uv;
  if (!model.unproject_ray(pixel, &ray)) return false;
  const int n = model.num_params();
  Eigen::Matrix<double, 2, Eigen::Dynamic> J(2, n);
  with_lens_model(model.lens_model(), [&](auto lm) {
    Eigen::Matrix<double, 2, 3> Jc;
    decltype(lm)::project_jacobians(model.params().data(), ray, &uv.x(), &uv.y(), &Jc, J.data());
  });
  Jf->resize(2, static_cast<Eigen::Index>(free_idx.size()));
  for (size_t k = 0; k < free_idx.size(); ++k) Jf->col(static_cast<Eigen::Index>(k)) = J.col(free_idx[k]);
  return true;
}

Eigen::MatrixXd projection_gram(const CameraModel& model, const std::vector<bool>& fixed, int cols, int rows) {
  const int n = model.num_params();
  if (static_cast<int>(fixed.size()) != n) throw Error(ErrorCode::kInvalidArgument, "projection_gram: fixed size");
  if (cols < 1 || rows < 1) throw Error(ErrorCode::kInvalidArgument, "projection_gram: grid must be >= 1x1");
  const std::vector<int> free_idx = free_intrinsics(fixed);
  const int m = static_cast<int>(free_idx.size());
  Eigen::MatrixXd G = Eigen::MatrixXd::Zero(m, m);
  Eigen::Matrix<double, 2, Eigen::Dynamic> Jf(2, m);
  int count = 0;
  for (int j = 0; j < rows; ++j) {
    for (int i = 0; i < cols; ++i) {
      const Eigen::Vector2d p((i + 0.5) * model.width() / cols - 0.5, (j + 0.5) * model.height() / rows - 0.5);
      if (!ray_intrinsics_jacobian(model, free_idx, p, &Jf)) continue;
      G.noalias() += Jf.transpose() * Jf;
      ++count;
    }
  }
  if (count > 0) G /= count;
  return G;
}

}  // namespace posecal
