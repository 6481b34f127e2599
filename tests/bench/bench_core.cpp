// Core benchmarks: calibration (bundle adjustment + covariance), detection, rendering.
// Run on one core: taskset -c 0 build/bin/bench_core --benchmark_repetitions=10
//   --benchmark_report_aggregates_only=true   (docs/performance.md)
#include <benchmark/benchmark.h>

#include <optional>
#include <random>

#include "board/tracking.hpp"
#include "board/views.hpp"
#include "calib/calibration.hpp"
#include "calib/information.hpp"
#include "lens/reference_models.hpp"
#include "select/engine.hpp"
#include "select/pose_rules.hpp"
#include "select/view_candidates.hpp"
#include "sim/synthetic.hpp"

using namespace posecal;

namespace {

struct Fixture {
  CameraModel truth = c525_reference_model();
  Board board;
  std::vector<Observation> frames;  // 10 frames x 40 corners
  CalibrationResult nine;           // solution from the first 9 frames
  cv::Mat frame_with_board, frame_without_board;
  Fixture() {
    RenderOptions ro;
    ro.noise_sigma = 2;
    ro.blur_sigma_px = 0.8;
    SyntheticCamera sc(truth, board, ro);
    uint64_t seed = 77;
    while (frames.size() < 10) {
      for (const Pose& p : random_board_views(seed++, 10, truth, board)) {
        const Detection d = board.detect(sc.render(p));
        if (d.size() == 40 && frames.size() < 10) frames.push_back(Observation::from(d));
      }
    }
    nine = calibrate(std::vector<Observation>(frames.begin(), frames.begin() + 9), truth.size());
    frame_with_board = sc.render(random_board_views(3, 1, truth, board)[0]);
    Pose away;
    away.t = Eigen::Vector3d(0, 0, -1);
    frame_without_board = sc.render(away);
  }
};

Fixture& fixture() {
  static Fixture f;
  return f;
}

}  // namespace

// The live loop's case: one keyframe more, warm-started from the previous solution
// (bundle adjustment over 9 intrinsics + 10 poses, 800 residuals, then the full covariance).
static void BM_Recalibrate_10x40_WarmStart(benchmark::State& state) {
  Fixture& f = fixture();
  const WarmStart ws{f.nine.model, f.nine.poses};
  for (auto _ : state) {
    CalibrationResult r = calibrate(f.frames, f.truth.size(), {}, &ws);
    benchmark::DoNotOptimize(r.covariance.data());
  }
}
BENCHMARK(BM_Recalibrate_10x40_WarmStart)->Unit(benchmark::kMillisecond);

// Bundle adjustment plus covariance from Zhang's initial solution (pinhole, no distortion, poses
// from PnP), computed outside the timed region: the solver's own cost from a cold start.
static void BM_BundleAdjust_10x40_FromZhangInit(benchmark::State& state) {
  Fixture& f = fixture();
  CalibrationOptions zhang;
  zhang.zero_distortion = true;
  const CalibrationResult init = calibrate(f.frames, f.truth.size(), zhang);
  const WarmStart ws{init.model, init.poses};
  for (auto _ : state) {
    CalibrationResult r = calibrate(f.frames, f.truth.size(), {}, &ws);
    benchmark::DoNotOptimize(r.covariance.data());
  }
  state.counters["iterations"] = calibrate(f.frames, f.truth.size(), {}, &ws).iterations;
}
BENCHMARK(BM_BundleAdjust_10x40_FromZhangInit)->Unit(benchmark::kMillisecond);

// From scratch: OpenCV's Zhang initialisation, then bundle adjustment and covariance.
static void BM_Calibrate_10x40_Cold(benchmark::State& state) {
  Fixture& f = fixture();
  for (auto _ : state) {
    CalibrationResult r = calibrate(f.frames, f.truth.size());
    benchmark::DoNotOptimize(r.covariance.data());
  }
}
BENCHMARK(BM_Calibrate_10x40_Cold)->Unit(benchmark::kMillisecond);

static void BM_DetectCharuco_1280x720(benchmark::State& state) {
  Fixture& f = fixture();
  DetectorOptions o;
  for (auto _ : state) {
    Detection d = f.board.detect(f.frame_with_board, o);
    if (d.size() < 30) state.SkipWithError("board not found");
    benchmark::DoNotOptimize(d.image_points.data());
  }
}
BENCHMARK(BM_DetectCharuco_1280x720)->Unit(benchmark::kMillisecond);

// The same frame searched as a tracked one (core/board/tracking.hpp): around the board found in
// it, on a copy shrunk as far as the markers stay resolved.
static void BM_DetectCharuco_1280x720_Tracked(benchmark::State& state) {
  Fixture& f = fixture();
  const Detection last = f.board.detect(f.frame_with_board);
  const TrackingPlan plan = plan_tracking(f.board, last, f.frame_with_board.size());
  for (auto _ : state) {
    Detection d = f.board.detect_in(f.frame_with_board, plan.region, plan.shrink,
                                    plan.min_perimeter_px, plan.max_perimeter_px);
    if (d.size() < last.size()) state.SkipWithError("the tracked search found fewer corners");
    benchmark::DoNotOptimize(d.image_points.data());
  }
  state.counters["shrink"] = plan.shrink;
  state.counters["region_share"] =
      static_cast<double>(plan.region.area()) / static_cast<double>(f.frame_with_board.total());
}
BENCHMARK(BM_DetectCharuco_1280x720_Tracked)->Unit(benchmark::kMillisecond);

static void BM_DetectCharuco_1280x720_NoBoard(benchmark::State& state) {
  Fixture& f = fixture();
  for (auto _ : state) {
    Detection d = f.board.detect(f.frame_without_board);
    benchmark::DoNotOptimize(d.ids.data());
  }
}
BENCHMARK(BM_DetectCharuco_1280x720_NoBoard)->Unit(benchmark::kMillisecond);

static void BM_RenderFrame_1280x720(benchmark::State& state) {
  Fixture& f = fixture();
  RenderOptions ro;
  ro.noise_sigma = 2;
  ro.blur_sigma_px = 0.8;
  SyntheticCamera sc(f.truth, f.board, ro);
  const Pose p = random_board_views(5, 1, f.truth, f.board)[0];
  for (auto _ : state) {
    cv::Mat img = sc.render(p);
    benchmark::DoNotOptimize(img.data);
  }
}
BENCHMARK(BM_RenderFrame_1280x720)->Unit(benchmark::kMillisecond);

// Target pose generation, the paper's rule: the next C_K pose (sequence element, roll, shift,
// moved back to stay in view) for cx.
static void BM_TargetPose_Pinhole_PaperRule(benchmark::State& state) {
  Fixture& f = fixture();
  PoseGenerator pg(f.board, f.truth.size());
  for (auto _ : state) {
    TargetPose t = pg.next_pose(2, f.nine.model);
    benchmark::DoNotOptimize(t.T_cam_board.t.data());
  }
}
BENCHMARK(BM_TargetPose_Pinhole_PaperRule)->Unit(benchmark::kMicrosecond);

// The paper's C_Delta rule: distortion map of the estimate, threshold search for the most
// distorted unvisited region, board placement; the mask is reset so every call searches anew.
static void BM_TargetPose_Distortion_PaperRule(benchmark::State& state) {
  Fixture& f = fixture();
  for (auto _ : state) {
    state.PauseTiming();
    PoseGenerator pg(f.board, f.truth.size());
    state.ResumeTiming();
    TargetPose t = pg.next_pose(4, f.nine.model);
    benchmark::DoNotOptimize(t.T_cam_board.t.data());
  }
}
BENCHMARK(BM_TargetPose_Distortion_PaperRule)->Unit(benchmark::kMicrosecond);

// The engine's default: 6 rule-generated candidates, each scored by the predicted variance of
// the targeted parameter (Schur complement of its 40 corners' information), as the engine does.
static void BM_TargetPose_Scored6(benchmark::State& state) {
  Fixture& f = fixture();
  const int param = static_cast<int>(state.range(0));
  const Eigen::MatrixXd info = intrinsics_information(f.nine);
  for (auto _ : state) {
    state.PauseTiming();
    PoseGenerator pg(f.board, f.truth.size());
    state.ResumeTiming();
    auto score = [&](const TargetPose& t) {
      const Eigen::MatrixXd I = info + frame_information(f.nine.model, t.T_cam_board, f.board.corners(), f.nine.fixed);
      return Eigen::MatrixXd(I.ldlt().solve(Eigen::MatrixXd::Identity(9, 9)))(param, param);
    };
    TargetPose t = pg.next_pose(param, f.nine.model, score, 6);
    benchmark::DoNotOptimize(t.T_cam_board.t.data());
  }
}
BENCHMARK(BM_TargetPose_Scored6)->Arg(2)->Arg(4)->Unit(benchmark::kMicrosecond);

// The engine's default since candidate_score = kProjection, step for step: the projection Gram
// matrix of the estimate (8x5 rays, as the engine), 6 rule candidates, each with its predicted covariance,
// the targeted parameter's variance (prospective test) and trace(G Sigma') (the score), then
// the best one committed.
static void BM_TargetPose_ProjectionScored6(benchmark::State& state) {
  Fixture& f = fixture();
  const int param = static_cast<int>(state.range(0));
  const Eigen::MatrixXd info = intrinsics_information(f.nine);
  for (auto _ : state) {
    state.PauseTiming();
    PoseGenerator pg(f.board, f.truth.size());
    state.ResumeTiming();
    const Eigen::MatrixXd G = projection_gram(f.nine.model, f.nine.fixed, 8, 5);
    const std::vector<TargetPose> cands = pg.candidates(param, f.nine.model, 6);
    size_t pick = 0;
    double best = 1e300, best_var = 1e300;
    for (size_t i = 0; i < cands.size(); ++i) {
      const Eigen::MatrixXd I = info + frame_information(f.nine.model, cands[i].T_cam_board, f.board.corners(), f.nine.fixed);
      const Eigen::MatrixXd cov = I.ldlt().solve(Eigen::MatrixXd::Identity(9, 9));
      best_var = std::min(best_var, cov(param, param));
      const double sc = (G * cov).trace();
      if (sc < best) best = sc, pick = i;
    }
    pg.commit(cands[pick]);
    benchmark::DoNotOptimize(best_var);
    benchmark::DoNotOptimize(cands[pick].T_cam_board.t.data());
  }
}
BENCHMARK(BM_TargetPose_ProjectionScored6)->Arg(2)->Arg(4)->Unit(benchmark::kMicrosecond);

// As above with EngineOptions::view_candidates = N, through the engine's ViewCandidates: N views
// of the whole board (the engine's ViewSampler: tilt <= 40 deg, 40-80% of the width, 2% margin),
// drawn outside the timing as the engine draws them, 100 per frame, in the frames before the
// choice (BM_ViewSampler_100 times that), here under an earlier estimate (the 8-frame solution);
// timed: their outline checked and each screened under the current estimate, the shortlist of
// 12 checked densely and predicted exactly; the best score wins among them and the 6 rule
// candidates (the engine's free choice).
static void BM_TargetPose_ProjectionScored6_Views(benchmark::State& state) {
  Fixture& f = fixture();
  const int param = static_cast<int>(state.range(0));
  const Eigen::MatrixXd info = intrinsics_information(f.nine);
  const int n_views = static_cast<int>(state.range(1));
  ViewSampling vs;
  vs.max_tilt_deg = 40;
  vs.min_width_fraction = 0.4;
  vs.max_width_fraction = 0.8;
  vs.margin_px = 0.02 * std::max(f.truth.width(), f.truth.height());
  const CalibrationResult eight = calibrate(std::vector<Observation>(f.frames.begin(), f.frames.begin() + 8), f.truth.size());
  const ViewSampler sampler(eight.model, f.board, vs);
  std::vector<std::vector<ViewPose>> pools(8);
  std::mt19937_64 rng(1);
  for (std::vector<ViewPose>& pool : pools) {
    pool.resize(static_cast<size_t>(n_views));
    for (ViewPose& v : pool) sampler.draw(rng, &v.R, &v.t);
  }
  ViewCandidateOptions vo;
  vo.count = n_views;
  vo.margin_px = vs.margin_px;
  vo.shortlist = 12;
  size_t screened = 0, picked_view = 0, runs = 0;
  for (auto _ : state) {
    state.PauseTiming();
    PoseGenerator pg(f.board, f.truth.size());
    const std::vector<ViewPose>& pool = pools[runs % pools.size()];
    state.ResumeTiming();
    const Eigen::MatrixXd G = projection_gram(f.nine.model, f.nine.fixed, 8, 5);
    const std::vector<TargetPose> cands = pg.candidates(param, f.nine.model, 6);
    std::vector<double> score, var;
    for (const TargetPose& c : cands) {
      const Eigen::MatrixXd I = info + frame_information(f.nine.model, c.T_cam_board, f.board.corners(), f.nine.fixed);
      const Eigen::MatrixXd cov = I.ldlt().solve(Eigen::MatrixXd::Identity(9, 9));
      var.push_back(cov(param, param));
      score.push_back((G * cov).trace());
    }
    ViewCandidates views(f.nine.model, f.board, f.nine.fixed, info, G, pool, vo);
    const std::vector<ViewCandidates::Exact> shortlist = views.shortlist(-1);
    for (const ViewCandidates::Exact& v : shortlist) {
      var.push_back(v.prediction.variance(param));
      score.push_back(v.prediction.projection);
    }
    const size_t pick = choose_candidate(score, var, cands.size(), false);
    const TargetPose& chosen = pick < cands.size() ? cands[pick] : *shortlist[pick - cands.size()].target;
    if (pick < cands.size()) pg.commit(cands[pick]);
    screened += views.size();
    picked_view += pick >= cands.size();
    ++runs;
    benchmark::DoNotOptimize(var[pick]);
    benchmark::DoNotOptimize(chosen.T_cam_board.t.data());
  }
  state.counters["views"] = static_cast<double>(screened) / std::max<size_t>(1, runs);
  state.counters["view_won"] = static_cast<double>(picked_view) / std::max<size_t>(1, runs);
}
BENCHMARK(BM_TargetPose_ProjectionScored6_Views)->Args({2, 100})->Args({2, 300})->Args({4, 300})->Unit(benchmark::kMicrosecond);

// The engine's per-frame share of drawing view candidates: 100 views with ViewSampler (the
// engine's sampling), added to a live-loop frame while a target choice is ahead.
static void BM_ViewSampler_100(benchmark::State& state) {
  Fixture& f = fixture();
  ViewSampling vs;
  vs.max_tilt_deg = 40;
  vs.min_width_fraction = 0.4;
  vs.max_width_fraction = 0.8;
  vs.margin_px = 0.02 * std::max(f.truth.width(), f.truth.height());
  std::mt19937_64 rng(1);
  for (auto _ : state) {
    const ViewSampler sampler(f.nine.model, f.board, vs);
    std::vector<ViewPose> pool(100);
    for (ViewPose& v : pool) sampler.draw(rng, &v.R, &v.t, nullptr, 200);
    benchmark::DoNotOptimize(pool.data());
  }
}
BENCHMARK(BM_ViewSampler_100)->Unit(benchmark::kMicrosecond);

// frame_information() alone: one view of the 40-corner board (the unit of every candidate score).
static void BM_FrameInformation_40Corners(benchmark::State& state) {
  Fixture& f = fixture();
  const Pose T = random_board_views(7, 1, f.truth, f.board)[0];
  for (auto _ : state) {
    const Eigen::MatrixXd I = frame_information(f.nine.model, T, f.board.corners(), f.nine.fixed);
    benchmark::DoNotOptimize(I.data());
  }
}
BENCHMARK(BM_FrameInformation_40Corners)->Unit(benchmark::kMicrosecond);

// The projection Gram matrix alone, over the engine's 8x5 rays and the benchmark's 40x23.
static void BM_ProjectionGram(benchmark::State& state) {
  Fixture& f = fixture();
  const int cols = static_cast<int>(state.range(0)), rows = static_cast<int>(state.range(1));
  for (auto _ : state) {
    const Eigen::MatrixXd G = projection_gram(f.nine.model, f.nine.fixed, cols, rows);
    benchmark::DoNotOptimize(G.data());
  }
}
BENCHMARK(BM_ProjectionGram)->Args({8, 5})->Args({40, 23})->Unit(benchmark::kMicrosecond);

// One frame of the live loop while refining: detection, stillness, pose (PnP), Jaccard of the
// target and current board areas, guidance. The board is away from the target, so no keyframe.
static void BM_EngineFrame_1280x720(benchmark::State& state) {
  Fixture& f = fixture();
  RenderOptions ro;
  ro.noise_sigma = 2;
  ro.blur_sigma_px = 0.8;
  SyntheticCamera sc(f.truth, f.board, ro);
  EngineOptions eo;
  eo.robot = true;
  CalibrationEngine e(f.truth.size(), eo);
  const Pose start = board_pose_at(f.board, Eigen::Vector3d(0, 0, 0.5), 0.4, 0.5, 0.2);
  for (int i = 0; i < 200 && e.state() != EngineState::kRefining; ++i) {
    const Pose p = e.target() ? e.target()->T_cam_board : start;
    if (e.target() && i % 3 == 1) e.report_pose_reached();
    e.process(sc.render(p));
  }
  if (e.state() != EngineState::kRefining) {
    state.SkipWithError("engine did not reach refining");
    return;
  }
  const cv::Mat frame = sc.render(random_board_views(99, 1, f.truth, f.board)[0]);
  for (auto _ : state) {
    FrameReport r = e.process(frame);
    if (r.captured) state.SkipWithError("captured a keyframe: not a plain live-loop frame");
    benchmark::DoNotOptimize(r.jaccard);
  }
}
BENCHMARK(BM_EngineFrame_1280x720)->Unit(benchmark::kMillisecond);

BENCHMARK_MAIN();

