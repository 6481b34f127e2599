#include <gtest/gtest.h>

#include <opencv2/calib3d.hpp>

#include "calib/calibration.hpp"
#include "common/error.hpp"
#include "calib/metrics.hpp"
#include "sim/synthetic.hpp"
#include "board/views.hpp"
#include "lens/reference_models.hpp"
#include "calib/information.hpp"

using namespace posecal;

namespace {

std::vector<Observation> observe(SyntheticCamera& sc, const std::vector<Pose>& poses) {
  std::vector<Observation> out;
  for (const Pose& p : poses) {
    const Detection d = sc.board().detect(sc.render(p));
    if (d.size() >= 6) out.push_back(Observation::from(d));
  }
  return out;
}

RenderOptions noisy(uint64_t seed) {
  RenderOptions ro;
  ro.noise_sigma = 2.0;
  ro.blur_sigma_px = 0.8;
  ro.seed = seed;
  return ro;
}

}  // namespace

TEST(Calibration, RecoversEveryIntrinsicWithin3Sigma) {
  const CameraModel truth = c525_reference_model();
  const Board target;
  SyntheticCamera sc(truth, target, noisy(7));
  const auto frames = observe(sc, random_board_views(21, 20, truth, target));
  ASSERT_EQ(frames.size(), 20u);
  const CalibrationResult r = calibrate(frames, truth.size());
  EXPECT_TRUE(r.solver_converged()) << r.termination_message;
  EXPECT_EQ(r.rank_deficiency, 0);
  EXPECT_LT(r.rms_px, 0.2);
  for (int i = 0; i < 9; ++i) {
    const double err = r.model.params()[i] - truth.params()[i];
    EXPECT_LT(std::abs(err), 3 * r.std_scaled[i])
        << truth.param_names()[i] << " est " << r.model.params()[i] << " true " << truth.params()[i]
        << " std " << r.std_scaled[i];
    EXPECT_GT(r.std_scaled[i], 0);
  }
  EXPECT_LT(ground_truth_error(truth, r.model), 0.1);
}

TEST(Calibration, NoWorseThanOpenCVOnTheSameFrames) {
  const CameraModel truth = c525_reference_model();
  const Board target;
  SyntheticCamera sc(truth, target, noisy(8));
  const auto frames = observe(sc, random_board_views(22, 20, truth, target));
  const CalibrationResult r = calibrate(frames, truth.size());
  std::vector<std::vector<cv::Point3f>> obj;
  std::vector<std::vector<cv::Point2f>> img;
  for (const auto& f : frames) {
    obj.emplace_back(f.board_points.begin(), f.board_points.end());
    img.emplace_back(f.image_points.begin(), f.image_points.end());
  }
  cv::Mat K, D, std_intr, std_extr, per_view;
  std::vector<cv::Mat> rv, tv;
  const double cv_rms =
      cv::calibrateCamera(obj, img, truth.size(), K, D, rv, tv, std_intr, std_extr, per_view);
  const CameraModel cvm = CameraModel::opencv5(
      truth.width(), truth.height(), K.at<double>(0, 0), K.at<double>(1, 1), K.at<double>(0, 2),
      K.at<double>(1, 2),
      {D.at<double>(0), D.at<double>(1), D.at<double>(2), D.at<double>(3), D.at<double>(4)});
  const double ours = ground_truth_error(truth, r.model), theirs = ground_truth_error(truth, cvm);
  std::printf("eps_gt ours %.5f px, OpenCV %.5f px; rms ours %.5f OpenCV %.5f\n", ours, theirs,
              r.rms_px, cv_rms);
  EXPECT_LE(ours, theirs + 1e-4);
  EXPECT_LE(r.rms_px, cv_rms + 1e-6);
  // Same covariance structure as OpenCV's own (J^T J)^-1 scaled by a residual variance; OpenCV
  // 4.6 divides the sum of squared residuals by (points - unknowns) instead of
  // (2 * points - unknowns), overstating sigma by sqrt((2N - U) / (N - U)) (docs/math.md).
  const double N = r.num_points, U = r.num_unknowns;
  const double opencv_factor = std::sqrt((N - U) / (2 * N - U));
  for (int i = 0; i < 9; ++i) {
    EXPECT_NEAR(r.std_scaled[i] / std_intr.at<double>(i), opencv_factor, 0.02 * opencv_factor)
        << truth.param_names()[i];
  }
}

TEST(Calibration, WarmStartMatchesColdStart) {
  const CameraModel truth = c525_reference_model();
  const Board target;
  SyntheticCamera sc(truth, target, noisy(9));
  auto frames = observe(sc, random_board_views(23, 11, truth, target));
  const std::vector<Observation> first(frames.begin(), frames.end() - 1);
  const CalibrationResult r10 = calibrate(first, truth.size());
  const WarmStart ws{r10.model, r10.poses};
  const CalibrationResult warm = calibrate(frames, truth.size(), {}, &ws);
  const CalibrationResult cold = calibrate(frames, truth.size());
  for (int i = 0; i < 9; ++i) {
    EXPECT_NEAR(warm.model.params()[i], cold.model.params()[i],
                1e-6 * (1 + std::abs(cold.model.params()[i])));
    EXPECT_NEAR(warm.std_unit[i], cold.std_unit[i], 1e-6 * (1 + cold.std_unit[i]));
  }
  EXPECT_EQ(warm.covariance.rows(), 9 + 6 * 11);
}

TEST(Calibration, FocalOnlySingleFrameBootstrap) {
  const CameraModel truth = c525_reference_model();
  const Board target;
  SyntheticCamera sc(truth, target, noisy(10));
  // One view tilted 35 degrees: enough perspective to fix f with pp and distortion held.
  const Pose p = board_pose_at(target, Eigen::Vector3d(0, 0, 0.5), 0.3, 35 * M_PI / 180, 0.39);
  const auto frames = observe(sc, {p});
  ASSERT_EQ(frames.size(), 1u);
  CalibrationOptions o;
  o.fix_principal_point = true;
  o.fix_aspect_ratio = true;
  o.zero_distortion = true;
  const CalibrationResult r = calibrate(frames, truth.size(), o);
  EXPECT_NEAR(r.model.cx(), (truth.width() - 1) * 0.5, 1e-9);
  EXPECT_NEAR(r.model.cy(), (truth.height() - 1) * 0.5, 1e-9);
  EXPECT_DOUBLE_EQ(r.model.params()[4], 0.0);
  EXPECT_NEAR(r.model.fx(), truth.fx(), 0.05 * truth.fx());
  EXPECT_NEAR(r.model.fy() / r.model.fx(), 1.0, 1e-9);
  EXPECT_EQ(r.std_unit[2], 0.0);  // fixed parameters have no variance
  EXPECT_GT(r.std_unit[0], 0.0);
  EXPECT_NEAR(r.std_unit[1], r.std_unit[0], 1e-9 * r.std_unit[0]);
}

TEST(Calibration, FrontoParallelViewsAreDegenerate) {
  const CameraModel truth =
      CameraModel::opencv5(1280, 720, 1000, 1000, 639.5, 359.5, {0, 0, 0, 0, 0});
  const Board target;
  SyntheticCamera sc(truth, target, noisy(11));
  std::vector<Pose> poses;
  for (int i = 0; i < 6; ++i) {
    poses.push_back(board_pose_at(
        target, Eigen::Vector3d(-0.1 + 0.04 * i, 0.02 * (i % 3) - 0.02, 0.45 + 0.03 * i), 0.0, 0.0,
        0.1 * i));
  }
  const auto frames = observe(sc, poses);
  ASSERT_EQ(frames.size(), 6u);
  try {
    calibrate(frames, truth.size());
    FAIL() << "fronto-parallel views accepted";
  } catch (const Error& e) {
    EXPECT_EQ(e.code(), ErrorCode::kDegenerate) << e.what();
    std::printf("fronto-parallel: %s\n", e.what());
  }
}

TEST(Calibration, BadInputGivesClearErrors) {
  const cv::Size size(640, 480);
  EXPECT_THROW(calibrate({}, size), Error);
  Observation few;
  few.image_points = {{1, 1}, {2, 2}, {3, 3}};
  few.board_points = {{0, 0, 0}, {1, 0, 0}, {0, 1, 0}};
  try {
    calibrate({few}, size);
    FAIL();
  } catch (const Error& e) {
    EXPECT_EQ(e.code(), ErrorCode::kDegenerate);
    EXPECT_NE(std::string(e.what()).find("at least 4"), std::string::npos) << e.what();
  }
  Observation nan = few;
  nan.image_points.push_back({NAN, 1});
  nan.board_points.push_back({1, 1, 0});
  try {
    calibrate({nan}, size);
    FAIL();
  } catch (const Error& e) {
    EXPECT_EQ(e.code(), ErrorCode::kInvalidArgument);
    EXPECT_NE(std::string(e.what()).find("non-finite"), std::string::npos) << e.what();
  }
  Observation four = few;
  four.image_points.push_back({4, 1});
  four.board_points.push_back({1, 1, 0});
  try {
    calibrate({four}, size);  // 8 constraints, 15 unknowns
    FAIL();
  } catch (const Error& e) {
    EXPECT_EQ(e.code(), ErrorCode::kDegenerate);
    EXPECT_NE(std::string(e.what()).find("too few points"), std::string::npos) << e.what();
  }
  Observation mismatch = four;
  mismatch.board_points.pop_back();
  EXPECT_THROW(calibrate({mismatch}, size), Error);
  CalibrationOptions o;
  o.fixed = {"k9"};
  EXPECT_THROW(calibrate({four}, size, o), Error);
  EXPECT_THROW(calibrate({four}, cv::Size(0, 0)), Error);
}

TEST(Metrics, GroundTruthErrorAndTestError) {
  const CameraModel truth = c525_reference_model();
  EXPECT_NEAR(ground_truth_error(truth, truth), 0.0, 1e-9);
  CameraModel shifted = truth;
  shifted.params()[2] += 1.5;  // cx off by 1.5 px: every ray lands 1.5 px away
  EXPECT_NEAR(ground_truth_error(truth, shifted), 1.5, 1e-9);
  const Board target;
  SyntheticCamera sc(truth, target);
  const auto test = observe(sc, test_set_views(truth, target, 10));
  const TestError te = test_error(truth, test);
  EXPECT_EQ(te.frames_used, 10);
  EXPECT_LT(te.rms_px, 0.1);
  CameraModel wrong = truth;
  wrong.params()[4] += 0.1;
  EXPECT_GT(test_error(wrong, test).rms_px, te.rms_px * 3);
}

// trace(G Sigma) is the expected squared projection error over the image: checked exactly for the
// principal point and the focal length of a pinhole model, and against sampling for a full
// covariance with distortion.
TEST(Calibration, ProjectionGramGivesTheExpectedProjectionError) {
  const CameraModel pin = CameraModel::opencv5(640, 480, 500, 500, 319.5, 239.5, {0, 0, 0, 0, 0});
  std::vector<bool> only(9, true);
  only[2] = false;  // cx free: every pixel moves by d(cx)
  Eigen::MatrixXd G = projection_gram(pin, only, 8, 6);
  ASSERT_EQ(G.rows(), 1);
  EXPECT_NEAR(G(0, 0), 1.0, 1e-9);
  only[2] = true;
  only[0] = false;  // fx free: pixel x moves by x_n d(fx)
  G = projection_gram(pin, only, 8, 6);
  double mean_x2 = 0;
  for (int i = 0; i < 8; ++i) {
    const double xn = ((i + 0.5) * 640 / 8 - 0.5 - 319.5) / 500;
    mean_x2 += xn * xn / 8;
  }
  EXPECT_NEAR(G(0, 0), mean_x2, 1e-9);

  // Full model: E|pi(C + dC) - pi(C)|^2 by sampling dC ~ N(0, Sigma), vs trace(G Sigma).
  const CameraModel m = c525_reference_model();
  const std::vector<bool> none(9, false);
  const Eigen::VectorXd sd = (Eigen::VectorXd(9) << 0.5, 0.5, 0.4, 0.4, 1e-3, 3e-3, 5e-5, 5e-5, 3e-3).finished();
  Eigen::MatrixXd corr = Eigen::MatrixXd::Identity(9, 9);
  corr(0, 1) = corr(1, 0) = 0.8;
  corr(4, 5) = corr(5, 4) = -0.6;
  const Eigen::MatrixXd Sigma = sd.asDiagonal() * corr * sd.asDiagonal();
  const double predicted = (projection_gram(m, none, 16, 9) * Sigma).trace();
  const Eigen::MatrixXd L = Sigma.llt().matrixL();
  cv::RNG rng(5);
  double sum = 0;
  const int samples = 2000;
  for (int s = 0; s < samples; ++s) {
    Eigen::VectorXd z(9);
    for (int k = 0; k < 9; ++k) z[k] = rng.gaussian(1.0);
    const Eigen::VectorXd d = L * z;
    CameraModel q = m;
    for (int k = 0; k < 9; ++k) q.params()[k] += d[k];
    double e = 0;
    int n = 0;
    for (int j = 0; j < 9; ++j) {
      for (int i = 0; i < 16; ++i) {
        const Eigen::Vector2d p((i + 0.5) * m.width() / 16 - 0.5, (j + 0.5) * m.height() / 9 - 0.5);
        Eigen::Vector2d xn, uv;
        ASSERT_TRUE(m.unproject(p, &xn));
        ASSERT_TRUE(q.project(Eigen::Vector3d(xn.x(), xn.y(), 1), &uv));
        e += (uv - p).squaredNorm();
        ++n;
      }
    }
    sum += e / n;
  }
  EXPECT_NEAR(sum / samples / predicted, 1.0, 0.08) << "sampled " << sum / samples << " predicted " << predicted;
  EXPECT_THROW(projection_gram(m, std::vector<bool>(3, false)), Error);
  EXPECT_THROW(projection_gram(m, none, 0, 9), Error);
}

// Weighted points: weight 1 is the unweighted sum, weights scale linearly; corner_quadrature()
// sums low-order polynomials over the corner grid exactly and stands in for the corners in
// frame_information() well enough to rank views (the engine checks its shortlist exactly).
TEST(Calibration, WeightedInformationAndCornerQuadrature) {
  const CameraModel m = CameraModel::opencv5(1280, 720, 1100, 1080, 650, 350, {-0.3, 0.15, 0.002, -0.001, -0.05});
  const Board board(BoardSpec{});
  const std::vector<bool> fixed(9, false);
  const Pose T = board_pose_at(board, Eigen::Vector3d(0.03, -0.02, 0.45), 0.7, 0.6, 0.4);
  const std::vector<cv::Point3d>& corners = board.corners();
  const Eigen::MatrixXd full = frame_information(m, T, corners, fixed);
  const Eigen::MatrixXd ones = frame_information(m, T, corners, std::vector<double>(corners.size(), 1.0), fixed);
  const Eigen::MatrixXd twos = frame_information(m, T, corners, std::vector<double>(corners.size(), 2.0), fixed);
  EXPECT_LT((ones - full).norm(), 1e-9 * full.norm());
  EXPECT_LT((twos - 2 * full).norm(), 1e-9 * full.norm());

  // Exact sums of x^a y^b over the 8x5 grid: a, b <= 5 with 3 nodes, <= 3 with 2.
  for (int nodes : {2, 3}) {
    std::vector<cv::Point3d> q;
    std::vector<double> w;
    corner_quadrature(corners, nodes, nodes, &q, &w);
    ASSERT_EQ(q.size(), static_cast<size_t>(nodes * nodes));
    for (int a = 0; a <= 2 * nodes - 1; ++a) {
      for (int b = 0; b <= 2 * nodes - 1; ++b) {
        double exact = 0, approx = 0;
        for (const cv::Point3d& c : corners) exact += std::pow(c.x, a) * std::pow(c.y, b);
        for (size_t i = 0; i < q.size(); ++i) approx += w[i] * std::pow(q[i].x, a) * std::pow(q[i].y, b);
        EXPECT_NEAR(approx, exact, 1e-9 * std::abs(exact)) << nodes << " nodes, x^" << a << " y^" << b;
      }
    }
    for (double wi : w) EXPECT_GT(wi, 0.0);
  }
  // Mixed: 3 nodes along x (8 values), 2 along y (5 values).
  std::vector<cv::Point3d> q;
  std::vector<double> w;
  corner_quadrature(corners, 3, 2, &q, &w);
  EXPECT_EQ(q.size(), 6u);
  // Not a full grid (a corner missing), or too few values per axis: the corners themselves.
  std::vector<cv::Point3d> partial(corners.begin() + 1, corners.end());
  corner_quadrature(partial, 3, 3, &q, &w);
  EXPECT_EQ(q.size(), partial.size());
  EXPECT_EQ(w, std::vector<double>(partial.size(), 1.0));
  const std::vector<cv::Point3d> tiny = {{0, 0, 0}, {1, 0, 0}, {0, 1, 0}, {1, 1, 0}};
  corner_quadrature(tiny, 2, 2, &q, &w);
  EXPECT_EQ(q.size(), 4u);
  EXPECT_EQ(w, std::vector<double>(4, 1.0));
  EXPECT_THROW(corner_quadrature(corners, 4, 3, &q, &w), Error);
  EXPECT_THROW(corner_quadrature(corners, 3, 1, &q, &w), Error);

  // The 3x3 quadrature's predicted standard deviations after this strongly tilted view, on top of
  // a weak prior, are within 30% of the exact ones (k3, the highest order, is the worst: 26%).
  corner_quadrature(corners, 3, 3, &q, &w);
  const Eigen::MatrixXd prior = 1e-2 * full.diagonal().asDiagonal().toDenseMatrix();
  const Eigen::MatrixXd ce = (prior + full).inverse(), ca = (prior + frame_information(m, T, q, w, fixed)).inverse();
  for (int i = 0; i < 9; ++i) EXPECT_NEAR(std::sqrt(ca(i, i) / ce(i, i)), 1.0, 0.3) << "parameter " << i;

  EXPECT_THROW(frame_information(m, T, corners, std::vector<double>(3, 1.0), fixed), Error);
  std::vector<double> bad(corners.size(), 1.0);
  bad[5] = -1;
  EXPECT_THROW(frame_information(m, T, corners, bad, fixed), Error);
  bad[5] = std::nan("");
  EXPECT_THROW(frame_information(m, T, corners, bad, fixed), Error);
}

// frame_information() against an independent computation: central differences of the projection
// in the rotation-vector parametrisation, then the Schur complement onto the free intrinsics.
TEST(Calibration, FrameInformationIsTheSchurComplementOfOneView) {
  const CameraModel m = CameraModel::opencv5(1280, 720, 1100, 1080, 650, 350, {-0.3, 0.15, 0.002, -0.001, -0.05});
  const Board board(BoardSpec{});
  const Pose T = board_pose_at(board, Eigen::Vector3d(0.03, -0.02, 0.45), 0.7, 0.6, 0.4);
  ASSERT_TRUE(board_fully_visible(m, board, T));
  for (const std::vector<bool>& fixed :
       {std::vector<bool>(9, false), std::vector<bool>{false, false, false, false, false, false, true, true, true}}) {
    std::vector<int> free_idx;
    for (int i = 0; i < 9; ++i)
      if (!fixed[i]) free_idx.push_back(i);
    const int f = static_cast<int>(free_idx.size());
    Eigen::MatrixXd A = Eigen::MatrixXd::Zero(f, f), B = Eigen::MatrixXd::Zero(f, 6), D = Eigen::MatrixXd::Zero(6, 6);
    auto project = [&](const CameraModel& mm, const Pose& p, const cv::Point3d& P) {
      Eigen::Vector2d uv;
      EXPECT_TRUE(mm.project(p.apply(Eigen::Vector3d(P.x, P.y, P.z)), &uv));
      return uv;
    };
    for (const cv::Point3d& P : board.corners()) {
      Eigen::MatrixXd Ji(2, f), Jp(2, 6);
      for (int k = 0; k < f; ++k) {
        const double h = 1e-6 * std::max(1.0, std::abs(m.params()[free_idx[k]]));
        CameraModel a = m, b = m;
        a.params()[free_idx[k]] += h;
        b.params()[free_idx[k]] -= h;
        Ji.col(k) = (project(a, T, P) - project(b, T, P)) / (2 * h);
      }
      for (int k = 0; k < 6; ++k) {
        const double h = 1e-7;
        Pose a = T, b = T;
        (k < 3 ? a.r : a.t)[k % 3] += h;
        (k < 3 ? b.r : b.t)[k % 3] -= h;
        Jp.col(k) = (project(m, a, P) - project(m, b, P)) / (2 * h);
      }
      A += Ji.transpose() * Ji;
      B += Ji.transpose() * Jp;
      D += Jp.transpose() * Jp;
    }
    const Eigen::MatrixXd expected = A - B * D.ldlt().solve(B.transpose());
    const Eigen::MatrixXd got = frame_information(m, T, board.corners(), fixed);
    ASSERT_EQ(got.rows(), f);
    ASSERT_EQ(got.cols(), f);
    // Compare in a scale-free way: the predicted standard deviations and correlations.
    const Eigen::MatrixXd ce = expected.inverse(), cg = got.inverse();
    for (int i = 0; i < f; ++i) {
      EXPECT_NEAR(std::sqrt(cg(i, i)) / std::sqrt(ce(i, i)), 1.0, 1e-4) << "parameter " << free_idx[i];
      for (int j = 0; j < i; ++j)
        EXPECT_NEAR(cg(i, j) / std::sqrt(cg(i, i) * cg(j, j)), ce(i, j) / std::sqrt(ce(i, i) * ce(j, j)), 1e-4);
    }
  }
  EXPECT_THROW(frame_information(m, T, board.corners(), std::vector<bool>(5, false)), Error);
}
