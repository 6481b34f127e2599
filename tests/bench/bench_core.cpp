// Core benchmarks: calibration (bundle adjustment + covariance), detection, rendering.
// Run on one core: taskset -c 0 build/bin/bench_core --benchmark_repetitions=10
//   --benchmark_report_aggregates_only=true   (docs/performance.md)
#include <benchmark/benchmark.h>

#include "posecal/calibration.hpp"
#include "posecal/synthetic.hpp"
#include "posecal/views.hpp"

using namespace posecal;

namespace {

struct Fixture {
  CameraModel truth = c525_reference_model();
  Target target;
  std::vector<Observation> frames;  // 10 frames x 40 corners
  CalibrationResult nine;           // solution from the first 9 frames
  cv::Mat frame_with_board, frame_without_board;
  Fixture() {
    RenderOptions ro;
    ro.noise_sigma = 2;
    ro.blur_sigma_px = 0.8;
    SyntheticCamera sc(truth, target, ro);
    uint64_t seed = 77;
    while (frames.size() < 10) {
      for (const Pose& p : random_board_views(seed++, 10, truth, target)) {
        const Detection d = target.detect(sc.render(p));
        if (d.size() == 40 && frames.size() < 10) frames.push_back(Observation::from(d));
      }
    }
    nine = calibrate(std::vector<Observation>(frames.begin(), frames.begin() + 9), truth.size());
    frame_with_board = sc.render(random_board_views(3, 1, truth, target)[0]);
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
    Detection d = f.target.detect(f.frame_with_board, o);
    if (d.size() < 30) state.SkipWithError("board not found");
    benchmark::DoNotOptimize(d.image_points.data());
  }
}
BENCHMARK(BM_DetectCharuco_1280x720)->Unit(benchmark::kMillisecond);

static void BM_DetectCharuco_1280x720_NoBoard(benchmark::State& state) {
  Fixture& f = fixture();
  for (auto _ : state) {
    Detection d = f.target.detect(f.frame_without_board);
    benchmark::DoNotOptimize(d.ids.data());
  }
}
BENCHMARK(BM_DetectCharuco_1280x720_NoBoard)->Unit(benchmark::kMillisecond);

static void BM_RenderFrame_1280x720(benchmark::State& state) {
  Fixture& f = fixture();
  RenderOptions ro;
  ro.noise_sigma = 2;
  ro.blur_sigma_px = 0.8;
  SyntheticCamera sc(f.truth, f.target, ro);
  const Pose p = random_board_views(5, 1, f.truth, f.target)[0];
  for (auto _ : state) {
    cv::Mat img = sc.render(p);
    benchmark::DoNotOptimize(img.data);
  }
}
BENCHMARK(BM_RenderFrame_1280x720)->Unit(benchmark::kMillisecond);

BENCHMARK_MAIN();
