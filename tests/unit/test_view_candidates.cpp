// The engine's generic view candidates: the sampler and its library, screening and the shortlist.
#include <gtest/gtest.h>

#include <cmath>
#include <random>

#include "calib/calibration.hpp"
#include "common/error.hpp"
#include "sim/synthetic.hpp"
#include "select/view_candidates.hpp"
#include "board/views.hpp"
#include "lens/reference_models.hpp"
#include "calib/information.hpp"

using namespace posecal;

namespace {

ViewSampling engine_sampling(const CameraModel& m) {
  ViewSampling vs;
  vs.max_tilt_deg = 40;
  vs.min_width_fraction = 0.4;
  vs.max_width_fraction = 0.8;
  vs.margin_px = 0.02 * std::max(m.width(), m.height());
  return vs;
}

double tilt_deg(const Eigen::Matrix3d& R) { return std::acos(std::min(1.0, std::abs(R(2, 2)))) * 180 / M_PI; }

// Width of the board's projected corners as a fraction of the image width.
double width_fraction(const CameraModel& m, const Board& board, const Eigen::Matrix3d& R, const Eigen::Vector3d& t) {
  double x0 = 1e9, x1 = -1e9;
  for (const cv::Point3d& c : board.outline()) {
    Eigen::Vector2d uv;
    EXPECT_TRUE(m.project(R * Eigen::Vector3d(c.x, c.y, c.z) + t, &uv));
    x0 = std::min(x0, uv.x()), x1 = std::max(x1, uv.x());
  }
  return (x1 - x0) / m.width();
}

// A calibration state to predict from: 4 random views of the truth.
struct State {
  CameraModel truth = c525_reference_model();
  Board board;
  CalibrationResult result;
  Eigen::MatrixXd information, gram;
  State() {
    std::vector<Observation> frames;
    for (const Pose& p : random_board_views(11, 4, truth, board)) {
      Observation o;
      int id = 0;
      for (const cv::Point3d& c : board.corners()) {
        o.ids.push_back(id++);
        Eigen::Vector2d uv;
        EXPECT_TRUE(truth.project(p.apply(Eigen::Vector3d(c.x, c.y, c.z)), &uv));
        o.image_points.emplace_back(uv.x(), uv.y());
        o.board_points.push_back(c);
      }
      frames.push_back(o);
    }
    result = calibrate(frames, truth.size());
    information = intrinsics_information(result);
    gram = projection_gram(result.model, result.fixed, 8, 5);
  }
};

std::vector<ViewPose> draw_pool(const CameraModel& m, const Board& board, uint64_t seed, int count) {
  const ViewSampler sampler(m, board, engine_sampling(m));
  std::mt19937_64 rng(seed);
  std::vector<ViewPose> out(static_cast<size_t>(count));
  for (ViewPose& v : out) EXPECT_TRUE(sampler.draw(rng, &v.R, &v.t));
  return out;
}

}  // namespace

// Sampled views keep their limits: the outline's corners in the image with the margin (and the
// dense check passes for nearly all), tilt <= 40 deg, the board about 40-80% of the width; the
// draw counts add up; a board that cannot fit ends after max_tries draws.
TEST(ViewSampler, DrawsKeepTheirLimits) {
  const CameraModel cam = c525_reference_model();
  const Board board;
  ViewSampling vs = engine_sampling(cam);
  const ViewSampler sampler(cam, board, vs);
  std::mt19937_64 rng(5);
  int dense_ok = 0;
  long total = 0;
  double min_w = 1, max_w = 0;
  for (int i = 0; i < 300; ++i) {
    Eigen::Matrix3d R;
    Eigen::Vector3d t;
    int draws = -1;
    ASSERT_TRUE(sampler.draw(rng, &R, &t, &draws));
    EXPECT_GE(draws, 1);
    total += draws;
    EXPECT_LE(tilt_deg(R), 40.0 + 1e-9);
    EXPECT_NEAR((R.transpose() * R - Eigen::Matrix3d::Identity()).norm(), 0.0, 1e-12);
    for (const cv::Point3d& o : board.outline()) {
      Eigen::Vector2d uv;
      ASSERT_TRUE(cam.project(R * Eigen::Vector3d(o.x, o.y, o.z) + t, &uv));
      EXPECT_GE(uv.x(), vs.margin_px);
      EXPECT_GE(uv.y(), vs.margin_px);
      EXPECT_LE(uv.x(), cam.width() - 1 - vs.margin_px);
      EXPECT_LE(uv.y(), cam.height() - 1 - vs.margin_px);
    }
    dense_ok += board_fully_visible(cam, board, Pose::from_rotation(R, t), vs.margin_px);
    const double w = width_fraction(cam, board, R, t);
    min_w = std::min(min_w, w), max_w = std::max(max_w, w);
  }
  EXPECT_GE(dense_ok, 295);
  EXPECT_GT(total, 300);   // some draws are rejected
  EXPECT_GT(min_w, 0.2);  // tilted and rolled boards look narrower than their depth says
  EXPECT_LT(max_w, 0.9);
  vs.margin_px = 400;  // nothing fits inside 1280x720 with 400 px margins
  vs.max_tries = 37;
  const ViewSampler none(cam, board, vs);
  int draws = -1;
  EXPECT_FALSE(none.draw(rng, &draws).has_value());
  EXPECT_EQ(draws, 37);
}

// Draws split into their intrinsics-free part and realise(): a draw realised under the sampler's
// own model puts the board's centre on the drawn pixel and passes board_outline_in_view; views
// drawn under one estimate mostly stay in view under a later one (the engine's pool).
TEST(ViewSampler, DrawsRealiseAndStayInViewUnderALaterEstimate) {
  const CameraModel truth = c525_reference_model();
  const Board board;
  const double f0 = std::max(truth.width(), truth.height());
  const CameraModel earlier = CameraModel::opencv5(truth.width(), truth.height(), f0, f0, (truth.width() - 1) * 0.5,
                                                   (truth.height() - 1) * 0.5, {0, 0, 0, 0, 0});
  const ViewSampling vs = engine_sampling(truth);
  const ViewSampler sampler(earlier, board, vs);
  std::mt19937_64 rng(42);
  const std::vector<cv::Point3d> outline = board.outline();
  int later_ok = 0;
  for (int i = 0; i < 200; ++i) {
    ViewDraw d;
    int draws = 0;
    ASSERT_TRUE(sampler.draw_view(rng, &d, &draws));
    EXPECT_GE(draws, 1);
    Eigen::Matrix3d R;
    Eigen::Vector3d t;
    if (!sampler.realise(d, &R, &t)) continue;
    EXPECT_TRUE(board_outline_in_view(earlier, outline, R, t, vs.margin_px));
    const cv::Size2d bs = board.board_size_m();
    Eigen::Vector2d uv;
    ASSERT_TRUE(earlier.project(R * Eigen::Vector3d(bs.width / 2, bs.height / 2, 0) + t, &uv));
    EXPECT_NEAR((uv - d.centre_px).norm(), 0.0, 1e-6);
    later_ok += board_outline_in_view(truth, outline, R, t, vs.margin_px);
  }
  EXPECT_GT(later_ok, 120);
  EXPECT_THROW(board_outline_in_view(truth, std::vector<cv::Point3d>(3), Eigen::Matrix3d::Identity(), Eigen::Vector3d(0, 0, 1), 0),
               Error);
}

// Screened predictions rank like the exact ones; the shortlist is the best screened, every entry
// passes the dense check and carries the exact prediction (the fast 9x9 path against LDLT).
TEST(ViewCandidates, ShortlistIsTheBestScreenedPredictedExactly) {
  const State st;
  const CameraModel& est = st.result.model;
  const ViewSampling vs = engine_sampling(est);
  const std::vector<ViewPose> lib = draw_pool(est, st.board, 7, 250);
  ViewCandidateOptions vo;
  vo.count = 200;
  vo.margin_px = vs.margin_px;
  vo.shortlist = 12;
  ViewCandidates views(est, st.board, st.result.fixed, st.information, st.gram, lib, vo);
  ASSERT_EQ(views.size(), 200u);
  const std::vector<ViewCandidates::Exact> list = views.shortlist(-1);
  ASSERT_GE(list.size(), 10u);
  ASSERT_LE(list.size(), 12u);
  double best_exact = 1e300;
  for (const ViewCandidates::Exact& e : list) {
    ASSERT_NE(e.target, nullptr);
    EXPECT_EQ(e.target->kind, TargetKind::kView);
    EXPECT_TRUE(board_fully_visible(est, st.board, e.target->T_cam_board, vs.margin_px));
    const CovariancePrediction ref = predict_covariance(
        st.information, st.gram, frame_information(est, e.target->T_cam_board, st.board.corners(), st.result.fixed));
    EXPECT_NEAR(e.prediction.projection, ref.projection, 1e-6 * ref.projection);
    ASSERT_EQ(e.prediction.variance.size(), ref.variance.size());
    for (int i = 0; i < ref.variance.size(); ++i) EXPECT_NEAR(e.prediction.variance(i), ref.variance(i), 1e-6 * ref.variance(i));
    best_exact = std::min(best_exact, e.prediction.projection);
  }
  // The exact best of all 200 is in the shortlist (or within 5% of it).
  double all_best = 1e300;
  for (size_t i = 0; i < 200; ++i) {
    const Pose p = Pose::from_rotation(lib[i].R, lib[i].t);
    if (!board_fully_visible(est, st.board, p, vs.margin_px)) continue;
    all_best = std::min(all_best, predict_covariance(st.information, st.gram,
                                                     frame_information(est, p, st.board.corners(), st.result.fixed))
                                      .projection);
  }
  EXPECT_LE(best_exact, 1.05 * all_best);
  // Cached: the same entries again; ranked by a variance, with a second ranking merged in.
  const std::vector<ViewCandidates::Exact> again = views.shortlist(-1);
  ASSERT_EQ(again.size(), list.size());
  for (size_t i = 0; i < list.size(); ++i) EXPECT_EQ(again[i].target, list[i].target);
  const std::vector<ViewCandidates::Exact> by_k1 = views.shortlist(4);
  const std::vector<ViewCandidates::Exact> both = views.shortlist(-1, 4);
  EXPECT_GE(both.size(), list.size());
  EXPECT_LE(both.size(), list.size() + by_k1.size());
  double best_k1 = 1e300;
  for (const auto& e : by_k1) best_k1 = std::min(best_k1, e.prediction.variance(4));
  double list_k1 = 1e300;
  for (const auto& e : list) list_k1 = std::min(list_k1, e.prediction.variance(4));
  EXPECT_LE(best_k1, 1.05 * list_k1);  // ranked for k1, the shortlist serves k1 at least as well
  // Misuse.
  EXPECT_THROW(views.shortlist(9), Error);
  ViewCandidates no_gram(est, st.board, st.result.fixed, st.information, Eigen::MatrixXd(), lib, vo);
  EXPECT_THROW(no_gram.shortlist(-1), Error);
  EXPECT_FALSE(no_gram.shortlist(2).empty());
  EXPECT_THROW(ViewCandidates(est, st.board, std::vector<bool>(5, false), st.information, st.gram, lib, vo), Error);
  EXPECT_THROW(ViewCandidates(est, st.board, st.result.fixed, Eigen::MatrixXd::Identity(3, 3), st.gram, lib, vo), Error);
  ViewCandidateOptions bad = vo;
  bad.shortlist = 0;
  EXPECT_THROW(ViewCandidates(est, st.board, st.result.fixed, st.information, st.gram, lib, bad), Error);
  // Fewer views than the count: all of them that are in view, no more; views out of view dropped.
  std::vector<ViewPose> few(lib.begin(), lib.begin() + 20);
  few[3].t.z() = -few[3].t.z();  // behind the camera
  few[5].t.x() += 5.0;           // far off to the side
  ViewCandidates some(est, st.board, st.result.fixed, st.information, st.gram, few, vo);
  EXPECT_EQ(some.size(), 18u);
}

// With fixed intrinsics (here the distortion) the general path predicts the free ones only.
TEST(ViewCandidates, FixedIntrinsicsArePredictedOverTheFreeOnes) {
  const State st;
  std::vector<bool> fixed(9, false);
  fixed[6] = fixed[7] = fixed[8] = true;  // p1 p2 k3
  std::vector<int> free_idx;
  for (int i = 0; i < 9; ++i)
    if (!fixed[i]) free_idx.push_back(i);
  Eigen::MatrixXd info(6, 6);
  for (int a = 0; a < 6; ++a)
    for (int b = 0; b < 6; ++b) info(a, b) = st.information(free_idx[a], free_idx[b]);
  const Eigen::MatrixXd G = projection_gram(st.result.model, fixed, 8, 5);
  const ViewSampling vs = engine_sampling(st.result.model);
  const std::vector<ViewPose> lib = draw_pool(st.result.model, st.board, 3, 60);
  ViewCandidateOptions vo;
  vo.count = 50;
  vo.margin_px = vs.margin_px;
  vo.shortlist = 5;
  ViewCandidates views(st.result.model, st.board, fixed, info, G, lib, vo);
  for (const auto& e : views.shortlist(-1)) {
    ASSERT_EQ(e.prediction.variance.size(), 6);
    const CovariancePrediction ref =
        predict_covariance(info, G, frame_information(st.result.model, e.target->T_cam_board, st.board.corners(), fixed));
    EXPECT_NEAR(e.prediction.projection, ref.projection, 1e-9 * ref.projection);
  }
}
