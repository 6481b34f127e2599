// The expected projection error (calib/expected_error.hpp) against the errors calibrations
// really make, and the accuracy_px stop rule of the engine in closed loop.
#include <gtest/gtest.h>
#include <unistd.h>

#include <cmath>
#include <cstdio>
#include <optional>
#include <random>

#include "../bench/camera_families.hpp"
#include "board/views.hpp"
#include "calib/calibration.hpp"
#include "calib/expected_error.hpp"
#include "calib/information.hpp"
#include "calib/metrics.hpp"
#include "common/error.hpp"
#include "io/model_file.hpp"
#include "io/result_file.hpp"
#include "lens/reference_models.hpp"
#include "session/session.hpp"
#include "sim/operator.hpp"
#include "sim/sim_camera.hpp"

using namespace posecal;

namespace {

// The board's corners seen at `views` through `truth`, each image point moved by N(0, sigma^2)
// per axis: the calibration's input without a renderer, so the noise is exactly known.
std::vector<Observation> noisy_views(const CameraModel& truth, const Board& board,
                                     const std::vector<Pose>& views, double sigma,
                                     std::mt19937_64* rng) {
  std::normal_distribution<double> noise(0.0, sigma);
  std::vector<Observation> out;
  for (const Pose& pose : views) {
    Observation o;
    const std::vector<cv::Point3d>& corners = board.corners();
    for (size_t i = 0; i < corners.size(); ++i) {
      const Eigen::Vector3d p =
          pose.apply(Eigen::Vector3d(corners[i].x, corners[i].y, corners[i].z));
      Eigen::Vector2d uv;
      if (!truth.project(p, &uv)) continue;
      if (uv.x() < 0 || uv.y() < 0 || uv.x() > truth.width() - 1 || uv.y() > truth.height() - 1)
        continue;
      o.ids.push_back(static_cast<int>(i));
      o.board_points.push_back(corners[i]);
      o.image_points.emplace_back(uv.x() + noise(*rng), uv.y() + noise(*rng));
    }
    if (o.size() >= 8) out.push_back(o);
  }
  return out;
}

// The realised counterpart of rms_px: the RMS over the same edge-to-edge grid of the distance
// between the true and the estimated projection of each true ray.
double realised_rms(const CameraModel& truth, const CameraModel& estimate, int cols, int rows) {
  return ground_truth_error_edges(truth, estimate, cols, rows, true);
}

}  // namespace

TEST(ExpectedError, PredictsTheRealisedErrorOverNoiseDraws) {
  // 20 random views, a known point noise of 0.05 px (what the renderer's corners show: eps_res
  // 0.03-0.05 px), so eps_gt is a few tenths of a pixel as in the benchmarks. Over 40 draws the
  // mean square of the realised error must match the mean square of the predictions (each
  // calibration's own, residual-scaled) to within the Monte-Carlo spread.
  const CameraModel truth = c525_reference_model();
  const Board board;
  const std::vector<Pose> views = random_board_views(77, 20, truth, board);
  std::mt19937_64 rng(5);
  double realised_ms = 0, predicted_ms = 0, predicted_unit_ms = 0;
  double realised_mean = 0, predicted_mean = 0;
  int within_p90 = 0;
  constexpr int kDraws = 40;
  for (int d = 0; d < kDraws; ++d) {
    const CalibrationResult r =
        calibrate(noisy_views(truth, board, views, 0.05, &rng), truth.size());
    const ExpectedError e = expected_error(r);
    ASSERT_EQ(e.points, kExpectedErrorPoints);
    const double realised = realised_rms(truth, r.model, kExpectedErrorCols, kExpectedErrorRows);
    realised_ms += realised * realised / kDraws;
    // The mean distance (what eps_gt measures) against its predicted distribution.
    const double distance = ground_truth_error_edges(truth, r.model);
    realised_mean += distance / kDraws;
    predicted_mean += e.mean_px / kDraws;
    within_p90 += distance <= e.p90_px;
    EXPECT_GT(e.p90_px, e.mean_px);
    predicted_ms += e.rms_px * e.rms_px / kDraws;
    predicted_unit_ms += e.rms_unit_px * e.rms_unit_px / kDraws;
  }
  const double ratio = std::sqrt(realised_ms / predicted_ms);
  std::printf("realised RMS %.4f px, predicted %.4f px (ratio %.3f); at 1 px noise %.4f px\n",
              std::sqrt(realised_ms), std::sqrt(predicted_ms), ratio, std::sqrt(predicted_unit_ms));
  EXPECT_GT(ratio, 0.8);
  EXPECT_LT(ratio, 1.25);
  std::printf("realised mean distance %.4f px, predicted %.4f px; within the predicted p90 in %d of %d\n",
              realised_mean, predicted_mean, within_p90, kDraws);
  EXPECT_GT(realised_mean / predicted_mean, 0.8);
  EXPECT_LT(realised_mean / predicted_mean, 1.25);
  // 90% expected: 40 draws give 36 +- 1.9.
  EXPECT_GE(within_p90, 31);
  EXPECT_LE(within_p90, 40);
  // The unit figure is the same prediction without the measured noise: 0.05 px of it.
  EXPECT_NEAR(std::sqrt(predicted_ms / predicted_unit_ms), 0.05, 0.005);
}

TEST(ExpectedError, MapIsThePerPointFigure) {
  const CameraModel truth = c525_reference_model();
  const Board board;
  std::mt19937_64 rng(9);
  const CalibrationResult r = calibrate(
      noisy_views(truth, board, random_board_views(78, 10, truth, board), 0.3, &rng), truth.size());
  const ExpectedError e = expected_error(r);
  const cv::Mat map = expected_error_map(r, kExpectedErrorCols, kExpectedErrorRows);
  ASSERT_EQ(map.type(), CV_32F);
  ASSERT_EQ(map.cols, kExpectedErrorCols);
  ASSERT_EQ(map.rows, kExpectedErrorRows);
  double ss = 0;
  for (int j = 0; j < map.rows; ++j)
    for (int i = 0; i < map.cols; ++i) {
      const float v = map.at<float>(j, i);
      ASSERT_TRUE(std::isfinite(v) && v > 0) << i << "," << j;
      ss += static_cast<double>(v) * v;
    }
  EXPECT_NEAR(std::sqrt(ss / map.total()), e.rms_px, 1e-5 * e.rms_px);
  // One value per pixel at the camera's size; its corners are the grid's corners.
  const cv::Mat full = expected_error_map(r, truth.width(), truth.height());
  ASSERT_EQ(full.size(), truth.size());
  EXPECT_NEAR(full.at<float>(0, 0), map.at<float>(0, 0), 1e-6);
  EXPECT_NEAR(full.at<float>(truth.height() - 1, truth.width() - 1),
              map.at<float>(map.rows - 1, map.cols - 1), 1e-6);
  EXPECT_THROW(expected_error_map(r, 1, 5), Error);
  EXPECT_THROW(expected_error(r, 5, 1), Error);
}

TEST(ExpectedError, LimitingParameterRemovesTheMostWhenKnown) {
  // Brute force: condition the covariance on each free intrinsic in turn and recompute the
  // expected error; the reported one must lower it most, by the reported share.
  const CameraModel truth = c525_reference_model();
  const Board board;
  std::mt19937_64 rng(11);
  CalibrationResult r = calibrate(
      noisy_views(truth, board, random_board_views(79, 6, truth, board), 0.3, &rng), truth.size());
  const ExpectedError e = expected_error(r);
  ASSERT_GE(e.limiting_param, 0);
  const int n = r.model.num_params();
  double best = -1;
  int best_k = -1;
  for (int k = 0; k < n; ++k) {
    CalibrationResult c = r;
    const Eigen::VectorXd col = r.covariance.col(k);
    c.covariance -= col * col.transpose() / r.covariance(k, k);
    const double after = expected_error(c).rms_px;
    const double share = 1 - after * after / (e.rms_px * e.rms_px);
    if (share > best) best = share, best_k = k;
  }
  EXPECT_EQ(e.limiting_param, best_k) << r.model.param_names()[best_k];
  EXPECT_NEAR(e.limiting_share, best, 1e-6);
}

namespace {

struct AccuracyRun {
  bool converged = false;
  std::string failure;
  int keyframes = 0;
  double expected = NAN, expected_p90 = NAN, eps_gt_rms = NAN;
};

AccuracyRun run_with_accuracy(int seed, double accuracy_px, int max_keyframes) {
  SimCameraOptions so;
  so.truth = sample_camera(c525_reference_model(), 0.1, 300 + seed);
  so.render.noise_sigma = 2.0;
  so.render.blur_sigma_px = 0.8;
  so.render.seed = seed;
  so.seed = seed;
  EngineOptions eo;
  eo.accuracy_px = accuracy_px;
  eo.max_keyframes = max_keyframes;
  eo.target_timeout_frames = (so.op.move_frames + so.op.hold_frames) * so.op.max_tries + 1;
  CalibrationSession s(make_sim_camera(so), eo);
  for (int f = 0; f < 2500 && !s.finished(); ++f) s.step(1000);
  AccuracyRun out;
  if (!s.has_engine() || !s.engine().result()) return out;
  const CalibrationEngine& eng = s.engine();
  out.converged = eng.converged();
  out.failure = eng.failure_reason();
  out.keyframes = eng.keyframes();
  out.expected = eng.expected_error()->rms_px;
  out.expected_p90 = eng.expected_error()->p90_px;
  out.eps_gt_rms =
      realised_rms(so.truth, eng.result()->model, kExpectedErrorCols, kExpectedErrorRows);
  return out;
}

}  // namespace

TEST(ExpectedError, AccuracyPxIsTheStopRule) {
  const AccuracyRun run = run_with_accuracy(1, 0.3, 30);
  ASSERT_TRUE(run.converged) << run.failure;
  // The stop figure is the 90th percentile of the realised error, which lies above the RMS.
  EXPECT_LE(run.expected_p90, 0.3);
  EXPECT_LT(run.expected, run.expected_p90);
  std::printf("accuracy_px 0.3: %d keyframes, expected %.3f px (p90 %.3f px), realised %.3f px\n",
              run.keyframes, run.expected, run.expected_p90, run.eps_gt_rms);
  EXPECT_LT(run.eps_gt_rms, 0.3 * 2);  // one draw: loose here, measured over many in the benchmark
}

TEST(ExpectedError, UnreachableAccuracyEndsWithTheReason) {
  const AccuracyRun run = run_with_accuracy(2, 0.001, 4);
  EXPECT_FALSE(run.converged);
  EXPECT_EQ(run.keyframes, 4);
  EXPECT_NE(run.failure.find("expected error of"), std::string::npos) << run.failure;
  EXPECT_NE(run.failure.find("accuracy_px 0.001 px"), std::string::npos) << run.failure;
  EXPECT_NE(run.failure.find("holds it back"), std::string::npos) << run.failure;
}

// A held parameter (CalibrationResult::held) is a guess the views did not confirm: the expected
// error counts it as unknown under its prior (held_covariance), never as known. Eight tilted
// boards near the middle of a strongly rational wide-angle lens (k4..k6 = 1.85, 0.6, 0.05) leave
// one of k4..k6 undetermined on 5 of 8 seeds; held, the estimate extrapolates to the rim 12-54 px
// off. Counted as unknown, the predicted RMS is 1.0-2.6 times what it was as known (seeds 1, 3, 7:
// p90 7.4 -> 15.6, 7.7 -> 20.1, 28.6 -> 59.6 px). It is not enough to cover every realised
// error (seeds 1 and 3 stay below it: the first-order prediction of a rational model's
// extrapolation beyond its data is short whatever is held; docs/pose-selection.md).
TEST(ExpectedError, HeldParametersCountAsUnknown) {
  const CameraModel truth(
      2448, 2048, LensModel::kOpenCV8,
      {1224, 1226, 1230.5, 1020.2, 1.5, 0.3, 0.0005, -0.0003, 0.01, 1.85, 0.6, 0.05});
  const Board board;
  int with_held = 0, covered = 0, covered_as_known = 0;
  double ratio_sum = 0;
  for (uint64_t seed = 1; seed <= 8; ++seed) {
    std::mt19937_64 rng(seed);
    std::uniform_real_distribution<double> u(-1, 1);
    std::vector<Pose> views;
    for (int k = 0; k < 8; ++k) {
      const double x = 0.03 * u(rng), y = 0.03 * u(rng), z = 0.25 + 0.05 * u(rng);
      const double axis = M_PI * u(rng), tilt = 0.5 + 0.2 * u(rng), roll = 0.3 * u(rng);
      views.push_back(board_pose_at(board, Eigen::Vector3d(x, y, z), axis, tilt, roll));
    }
    const std::vector<Observation> frames = noisy_views(truth, board, views, 0.05, &rng);
    CalibrationOptions o;
    o.lens_model = LensModel::kOpenCV8;
    o.hold_if_undetermined = {"k4", "k5", "k6"};
    const CalibrationResult r = calibrate(frames, truth.size(), o);
    if (r.held.empty()) {
      EXPECT_EQ(r.held_covariance.size(), 0) << seed;
      continue;
    }
    ++with_held;
    const int n = r.model.num_params();
    ASSERT_EQ(r.held_covariance.rows(), n) << seed;
    ASSERT_EQ(r.held_covariance.cols(), n) << seed;
    ASSERT_TRUE(r.held_covariance.allFinite()) << seed;
    EXPECT_LT((r.held_covariance - r.held_covariance.transpose()).norm(),
              1e-9 * r.held_covariance.norm());
    const std::vector<std::string>& names = r.model.param_names();
    for (int i = 0; i < n; ++i) {
      const bool held = std::find(r.held.begin(), r.held.end(), names[i]) != r.held.end();
      const double var = r.held_covariance(i, i) * r.residual_variance;
      if (held) {  // bounded by its prior, and not zero
        EXPECT_GT(var, 0.0) << seed << " " << names[i];
        EXPECT_LE(var, kHeldPriorStd * kHeldPriorStd * (1 + 1e-9)) << seed << " " << names[i];
      } else if (!r.fixed[i]) {  // opening more parameters does not make a variance smaller
        EXPECT_GE(r.held_covariance(i, i), r.covariance(i, i) * (1 - 1e-3))
            << seed << " " << names[i];
      }
    }
    const double realised = ground_truth_error_edges(truth, r.model);
    CalibrationResult as_known = r;
    as_known.held_covariance.resize(0, 0);
    const ExpectedError e = expected_error(r), known = expected_error(as_known);
    std::printf("seed %d: %zu held; predicted p90 %.2f px (as known %.2f px), realised %.2f px\n",
                static_cast<int>(seed), r.held.size(), e.p90_px, known.p90_px, realised);
    EXPECT_GE(e.rms_px, known.rms_px * (1 - 1e-6)) << seed;
    ratio_sum += e.rms_px / known.rms_px;
    covered += realised <= e.p90_px;
    covered_as_known += realised <= known.p90_px;
    // The map agrees with the figure it is the per-point form of (NaN where the ray does not
    // exist).
    const cv::Mat map = expected_error_map(r, kExpectedErrorCols, kExpectedErrorRows);
    double ms = 0;
    int points = 0;
    for (int j = 0; j < map.rows; ++j) {
      for (int i = 0; i < map.cols; ++i) {
        const double v = map.at<float>(j, i);
        if (std::isnan(v)) continue;
        ms += v * v;
        ++points;
      }
    }
    EXPECT_EQ(points, e.points) << seed;
    EXPECT_NEAR(std::sqrt(ms / points), e.rms_px, 1e-4 * e.rms_px) << seed;
    // Written to posecal's OpenCV file and read back (posecal report --result), the result gives
    // the same figure: the held coefficients and their covariance travel with it.
    CalibrationFileExtras extras;
    put_result_figures(r, &extras);
    ASSERT_EQ(extras.held, r.held) << seed;
    EXPECT_DOUBLE_EQ(extras.expected_error_px, e.rms_px) << seed;
    const std::string path = testing::TempDir() + "/held_" + std::to_string(getpid()) + ".yml";
    write_camera_model(path, r.model, extras);
    const ModelFile file = read_model_file(path);
    std::remove(path.c_str());
    EXPECT_EQ(file.extras.held, r.held) << seed;
    const std::optional<CalibrationResult> from_file = result_figures_of(file);
    ASSERT_TRUE(from_file.has_value()) << seed;
    const ExpectedError again = expected_error(*from_file);
    EXPECT_NEAR(again.rms_px, e.rms_px, 1e-6 * e.rms_px) << seed;
    EXPECT_NEAR(again.p90_px, e.p90_px, 1e-6 * e.p90_px) << seed;
  }
  ASSERT_GE(with_held, 3);
  EXPECT_GT(ratio_sum / with_held, 1.3);
  EXPECT_GE(covered, covered_as_known);
}

// Six random views of the board through the C525 reference lens, 0.05 px of noise: the input of
// a well-determined calibration.
namespace {
std::vector<Observation> six_c525_views(int views_seed, uint64_t noise_seed) {
  const CameraModel truth = c525_reference_model();
  const Board board;
  std::mt19937_64 rng(noise_seed);
  return noisy_views(truth, board, random_board_views(views_seed, 6, truth, board), 0.05, &rng);
}
}  // namespace

// The information the held covariance is made from is the calibration's own: with nothing held
// its inverse is the calibration's covariance of the free intrinsics (each frame's Schur
// complement against the bundle adjustment's pseudo-inverse of J^T J).
TEST(ExpectedError, InformationWithHeldIsTheCalibrationsOwn) {
  const CameraModel truth = c525_reference_model();
  const std::vector<Observation> frames = six_c525_views(31, 19);
  const CalibrationResult r = calibrate(frames, truth.size());
  ASSERT_TRUE(r.held.empty());
  std::vector<bool> open;
  const Eigen::MatrixXd info = information_with_held(r, frames, 1.0, &open);
  ASSERT_EQ(open, r.fixed);
  const std::vector<int> idx = free_intrinsics(open);
  const Eigen::MatrixXd C = info.inverse();
  for (size_t a = 0; a < idx.size(); ++a) {
    for (size_t b = 0; b < idx.size(); ++b) {
      const double want = r.covariance(idx[a], idx[b]);
      const double scale = std::sqrt(r.covariance(idx[a], idx[a]) * r.covariance(idx[b], idx[b]));
      EXPECT_NEAR(C(static_cast<Eigen::Index>(a), static_cast<Eigen::Index>(b)), want, 1e-6 * scale)
          << r.model.param_names()[static_cast<size_t>(idx[a])] << " "
          << r.model.param_names()[static_cast<size_t>(idx[b])];
    }
  }
}

// With a tied aspect ratio (fy = aspect fx, fy fixed in the result) fy's information is folded
// onto fx: the inverse is again the calibration's own covariance.
TEST(ExpectedError, InformationWithHeldFoldsATiedAspectRatio) {
  const CameraModel truth = c525_reference_model();
  const std::vector<Observation> frames = six_c525_views(37, 23);
  CalibrationOptions o;
  o.fix_aspect_ratio = true;
  const CalibrationResult r = calibrate(frames, truth.size(), o);
  ASSERT_TRUE(r.fixed[1]);
  std::vector<bool> open;
  const double aspect = r.model.fy() / r.model.fx();
  const Eigen::MatrixXd C = information_with_held(r, frames, 1.0, &open, aspect).inverse();
  const std::vector<int> idx = free_intrinsics(open);
  ASSERT_EQ(idx.front(), 0);
  for (size_t a = 0; a < idx.size(); ++a) {
    const double want = r.covariance(idx[a], idx[a]);
    EXPECT_NEAR(C(static_cast<Eigen::Index>(a), static_cast<Eigen::Index>(a)), want, 1e-6 * want)
        << r.model.param_names()[static_cast<size_t>(idx[a])];
  }
  // Unfolded (fy treated as fixed, not tied to fx), fx's variance is not the calibration's: the
  // fold is what makes it so.
  const Eigen::MatrixXd U = information_with_held(r, frames, 1.0, &open).inverse();
  EXPECT_GT(std::abs(U(0, 0) / r.covariance(0, 0) - 1), 0.01);
}

// An estimate that folds inside the image (part of it has no ray under the model) does not cover
// the image, and the expected error says so instead of quietly leaving those points out; every
// benchmark camera, and cameras sampled around each, covers its image.
TEST(ExpectedError, AnEstimateThatFoldsInsideTheImageDoesNotCoverIt) {
  const int grid = kExpectedErrorPoints;
  for (const char* family : {"c525", "industrial", "tele", "longfocal", "vga", "fisheye185",
                             "fisheye150", "wide", "tilted"}) {
    const CameraModel ref = reference_camera(family);
    EXPECT_EQ(grid_points_with_ray(ref), grid) << family;
    for (uint64_t seed = 1; seed <= 20; ++seed)
      EXPECT_EQ(grid_points_with_ray(sample_camera(ref, 0.1, seed)), grid) << family << " " << seed;
  }
  // A wide rational lens's estimate from keyframes that reach 0.68 of the image corners' radius,
  // k6 held at an early guess (bench_pose_selection, wide world, seed 1013): the image's corners
  // (16 of the grid's points) have no ray under it.
  const CameraModel folded(2448, 2048, LensModel::kOpenCV8,
                           {1070.9, 1026.3, 1163.7, 1038.8, 1.0334, -0.45589, 0.0005274,
                            -0.00032163, -0.035307, 0.97424, 0.00063453, -0.20259});
  const int with_ray = grid_points_with_ray(folded);
  EXPECT_EQ(with_ray, grid - 16);
  CalibrationResult r;
  r.model = folded;
  r.fixed.assign(folded.num_params(), false);
  r.covariance = Eigen::MatrixXd::Identity(folded.num_params(), folded.num_params()) * 1e-8;
  r.residual_variance = 1;
  const ExpectedError e = expected_error(r);
  EXPECT_FALSE(e.covers_image());
  EXPECT_EQ(e.points, with_ray);
  EXPECT_EQ(e.grid_points, grid);
  r.model = sample_camera(reference_camera("wide"), 0.1, 1013);
  EXPECT_TRUE(expected_error(r).covers_image());
}
