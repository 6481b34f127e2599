// Detection cost per frame against the frame size (issue 16): a frame of uniform noise (the
// worst case of the chessboard detector) and a frame showing the board, for the chessboard and
// the ChArUco board, at 1280x720, 3, 5, 12 and 48 MP; and the corner error against the true
// projections on the board frames (printed once per frame, before the timings). Then cluttered
// 1280x720 frames (a checkerboard texture of 10 or 14 px squares, grids of 12 or 16 px dots 8 px
// apart, the board in front of the 10 px checkerboard) and fuzz_session_feed's slow inputs
// (tests/fuzz/crashes/fuzz_session_feed/slow-*), issue 16's "cluttered frames"; the 1280x720 board
// and noise frames again with the clutter rules off (/no_cap), for their cost in one run. Then
// steep boards and boards partly out of view under sensor noise (BM_DetectSteep,
// BM_DetectPartial), the chessboard also with the quads' search alone (/quads_only).
//   taskset -c 0 build/bin/bench_detection --benchmark_repetitions=3
//       --benchmark_report_aggregates_only=true            (docs/performance.md)
// The frames are rendered once, on first use (a distortion-free lens; the 48 MP board frame is a
// 12 MP rendering scaled up twice, the simulator's limit being 32 MP).
#include <benchmark/benchmark.h>

#include <chrono>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <map>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <string>
#include <vector>

#include "board/board.hpp"
#include "board/views.hpp"
#include "fuzz_frames.hpp"
#include "lens/reference_models.hpp"
#include "sim/clutter.hpp"
#include "sim/synthetic.hpp"

using namespace posecal;

namespace {

struct FrameSize {
  const char* name;
  int width, height;
};

const std::vector<FrameSize>& sizes() {
  static const std::vector<FrameSize> s = {{"1280x720", 1280, 720},
                                           {"3MP", 2048, 1536},
                                           {"5MP", 2592, 1944},
                                           {"12MP", 4000, 3000},
                                           {"48MP", 8000, 6000}};
  return s;
}

const char* kChessboard = "chessboard:9x6:0.025";
const char* kCharuco = "charuco:9x6:0.028:0.0182:DICT_4X4_50";

// "chessboard" or "charuco": a board spec's type, as the benchmarks' names show it.
std::string board_kind(const std::string& spec) { return spec.substr(0, spec.find(':')); }

struct Scene {
  cv::Mat image;
  std::vector<cv::Point2d> truth;  // true corner projections (board frames only)
};

// The same view at every size: focal length 0.8 x width, the board about half the image wide,
// tilted 23 degrees, slightly rolled. A frame above the simulator's pixel limit (48 MP; the limit
// is 32 MP) is rendered at half the size and scaled up twice (bilinear; its blur and noise are
// twice as wide, and the truth is mapped to the large frame's pixel centres).
Scene render_board(const std::string& spec, const FrameSize& fs) {
  if (static_cast<long long>(fs.width) * fs.height > 32'000'000) {
    const FrameSize half{fs.name, fs.width / 2, fs.height / 2};
    Scene s = render_board(spec, half);
    cv::Mat large;
    cv::resize(s.image, large, cv::Size(fs.width, fs.height), 0, 0, cv::INTER_LINEAR);
    s.image = large;
    for (auto& p : s.truth) p = (p + cv::Point2d(0.5, 0.5)) * 2.0 - cv::Point2d(0.5, 0.5);
    return s;
  }
  const Board board(BoardSpec::parse(spec));
  const double f = 0.8 * fs.width;
  const CameraModel cam = CameraModel::opencv5(fs.width, fs.height, f, f, 0.5 * (fs.width - 1),
                                               0.5 * (fs.height - 1), {0, 0, 0, 0, 0});
  RenderOptions ro;
  ro.supersample = fs.width * fs.height > 20'000'000 ? 1 : 2;
  ro.noise_sigma = 2;
  ro.blur_sigma_px = 0.8;
  ro.seed = 5;
  SyntheticCamera sc(cam, board, ro);
  const Pose p = board_pose_at(board, Eigen::Vector3d(0.01, -0.005, 0.40), 0.7, 0.4, 0.2);
  Scene s;
  s.image = sc.render(p);
  s.truth = sc.true_corners(p);
  return s;
}

const Scene& scene(const std::string& spec, int size_index, bool noise) {
  static std::map<std::string, Scene> cache;
  const FrameSize& fs = sizes()[size_index];
  const std::string key = (noise ? std::string("noise") : spec) + "/" + fs.name;
  auto it = cache.find(key);
  if (it != cache.end()) return it->second;
  Scene s;
  if (noise) {
    s.image = cv::Mat(fs.height, fs.width, CV_8U);
    cv::RNG rng(16);
    rng.fill(s.image, cv::RNG::UNIFORM, 0, 256);
  } else {
    s = render_board(spec, fs);
  }
  return cache.emplace(key, std::move(s)).first->second;
}

void print_accuracy(const std::string& spec, const FrameSize& fs, const Scene& s,
                    const Detection& d) {
  double ss = 0, worst = 0;
  for (size_t i = 0; i < d.size(); ++i) {
    const double e = cv::norm(d.image_points[i] - s.truth[d.ids[i]]);
    ss += e * e;
    worst = std::max(worst, e);
  }
  std::fprintf(stderr, "accuracy %s %s: %zu corners, rms %.4f px, worst %.4f px\n", spec.c_str(),
               fs.name, d.size(), d.empty() ? 0.0 : std::sqrt(ss / d.size()), worst);
}

void BM_Detect(benchmark::State& state, std::string spec, int size_index, bool noise) {
  const Scene& s = scene(spec, size_index, noise);
  const Board board(BoardSpec::parse(spec));
  Detection d;
  for (auto _ : state) {
    try {
      d = board.detect(s.image);
    } catch (const std::exception& e) {
      state.SkipWithError(e.what());
      break;
    }
    benchmark::DoNotOptimize(d.image_points.data());
  }
  state.counters["corners"] = static_cast<double>(d.size());
  static std::map<std::string, bool> printed;
  if (!noise && !printed[spec + sizes()[size_index].name]) {
    printed[spec + sizes()[size_index].name] = true;
    print_accuracy(spec, sizes()[size_index], s, d);
  }
}

// Cluttered 1280x720 frames, by name.
const std::map<std::string, cv::Mat>& clutter_frames() {
  static const std::map<std::string, cv::Mat> frames = [] {
    const cv::Size hd(1280, 720);
    std::map<std::string, cv::Mat> f;
    f["checkerboard10"] = checkerboard_clutter(hd, 10);
    f["checkerboard14"] = checkerboard_clutter(hd, 14);
    f["dots12_8"] = dot_grid_clutter(hd, 12, 8);
    f["dots16_8"] = dot_grid_clutter(hd, 16, 8);
    for (const char* spec : {kChessboard, kCharuco}) {
      // The board of the 1280x720 board frame above, in front of the 10 px checkerboard.
      const Board board(BoardSpec::parse(spec));
      const double f_px = 0.8 * hd.width;
      const CameraModel cam =
          CameraModel::opencv5(hd.width, hd.height, f_px, f_px, 639.5, 359.5, {0, 0, 0, 0, 0});
      RenderOptions ro;
      ro.blur_sigma_px = 0.8;
      SyntheticCamera sc(cam, board, ro);
      const Pose p = board_pose_at(board, Eigen::Vector3d(0.01, -0.005, 0.40), 0.7, 0.4, 0.2);
      const std::string kind = board_kind(spec);
      f[kind + "_on_checkerboard10"] = render_in_front_of(sc, p, f["checkerboard10"]);
      if (kind == "chessboard") {
        // The same board farther away: squares of about 32 px, too small for the quarter-size
        // search (docs/performance.md, "Busy frames").
        const Pose far = board_pose_at(board, Eigen::Vector3d(0.01, -0.005, 0.80), 0.4, 0.3, 0.2);
        f[kind + "32px_on_checkerboard10"] = render_in_front_of(sc, far, f["checkerboard10"]);
      }
    }
    return f;
  }();
  return frames;
}

// The board on the C525 reference (1280x720) with its centre at `centre` (camera frame, metres),
// tilted by `tilt` radians about an in-plane axis at 0.4 rad and rolled 0.3 rad, under sensor
// noise of `noise` grey levels and blur `blur` px, without supersampling.
cv::Mat render_on_c525(const Board& board, double noise, double blur, const Eigen::Vector3d& centre,
                       double tilt) {
  RenderOptions ro;
  ro.blur_sigma_px = blur;
  ro.noise_sigma = noise;
  ro.supersample = 1;
  SyntheticCamera sc(c525_reference_model(), board, ro);
  return sc.render(board_pose_at(board, centre, 0.4, tilt, 0.3));
}

void BM_DetectFrame(benchmark::State& state, std::string spec, const cv::Mat* frame,
                    DetectorOptions options) {
  const Board board(BoardSpec::parse(spec));
  Detection d;
  for (auto _ : state) {
    d = board.detect(*frame, options);
    benchmark::DoNotOptimize(d.image_points.data());
  }
  state.counters["corners"] = static_cast<double>(d.size());
  state.counters["markers"] = d.markers;
}

void register_frame(const std::string& name, const std::string& spec, const cv::Mat* frame,
                    const DetectorOptions& options = {}) {
  benchmark::RegisterBenchmark(name.c_str(), BM_DetectFrame, spec, frame, options)
      ->Unit(benchmark::kMillisecond)
      ->MeasureProcessCPUTime()
      ->UseRealTime();
}

}  // namespace

int main(int argc, char** argv) {
  for (const char* spec : {kChessboard, kCharuco}) {
    const std::string kind = board_kind(spec);
    for (int i = 0; i < static_cast<int>(sizes().size()); ++i) {
      for (const bool noise : {true, false}) {
        const std::string name =
            "BM_Detect/" + kind + "/" + sizes()[i].name + (noise ? "/noise" : "/board");
        benchmark::RegisterBenchmark(name.c_str(), BM_Detect, std::string(spec), i, noise)
            ->Unit(benchmark::kMillisecond)
            ->MeasureProcessCPUTime()  // OpenCV's worker threads too
            ->UseRealTime();
      }
    }
  }
  // The cost of the clutter rules on frames they leave alone: the 1280x720 frames above with
  // the rules off (max_candidate_quads = 0: the detection before them), in the same run.
  DetectorOptions no_cap;
  no_cap.max_candidate_quads = 0;
  for (const char* spec : {kChessboard, kCharuco}) {
    const std::string kind = board_kind(spec);
    for (const bool noise : {true, false}) {
      register_frame("BM_Detect/" + kind + "/1280x720/" + (noise ? "noise" : "board") + "/no_cap",
                     spec, &scene(spec, 0, noise).image, no_cap);
    }
  }
  for (const char* spec : {kChessboard, kCharuco}) {
    const std::string kind = board_kind(spec);
    for (const auto& [name, frame] : clutter_frames()) {
      const bool board = name.find("_on_") != std::string::npos;
      if (!board || name.rfind(kind, 0) == 0)
        register_frame("BM_Detect/" + kind + "/1280x720/" + name, spec, &frame);
    }
  }
  // fuzz_session_feed's slow inputs, through Board::detect as the C ABI calls it.
  static std::map<std::string, cv::Mat> fuzz;
  namespace fs = std::filesystem;
  for (const auto& e : fs::directory_iterator(fs::path(POSECAL_SOURCE_DIR) /
                                              "tests/fuzz/crashes/fuzz_session_feed")) {
    const std::string name = e.path().filename().string();
    if (name.rfind("slow-", 0) == 0)
      fuzz[name] = testing_support::fuzz_session_frame(e.path().string());
  }
  for (const auto& [name, frame] : fuzz) register_frame("BM_DetectFuzz/" + name, kCharuco, &frame);
  // Scenes without a board (a circuit board, an aerial photo, a room, a painting, fruit) and one
  // with it (left01.jpg), from Debian's opencv-doc if it is installed: as they are (512-640 px)
  // and scaled up to 1280 px on the longer side (cubic), the camera's view while the operator
  // fetches the board. OpenCV's chessboard search tries all its thresholds when it finds nothing.
  static std::map<std::string, cv::Mat> scenes;
  const fs::path scene_dir = "/usr/share/doc/opencv-doc/examples/data";
  for (const char* file :
       {"board.jpg", "aero3.jpg", "home.jpg", "pic2.png", "apple.jpg", "left01.jpg"}) {
    const cv::Mat image = cv::imread((scene_dir / file).string(), cv::IMREAD_GRAYSCALE);
    if (image.empty()) continue;
    scenes[file] = image;
    const double s = 1280.0 / std::max(image.cols, image.rows);
    cv::resize(image, scenes[std::string(file) + "@1280"], cv::Size(), s, s, cv::INTER_CUBIC);
  }
  for (const char* spec : {kChessboard, kCharuco}) {
    for (const auto& [name, frame] : scenes)
      register_frame("BM_DetectScene/" + board_kind(spec) + "/" + name, spec, &frame);
  }
  // Steeply tilted boards under sensor noise, on the C525 reference (1280x720), rendered without
  // supersampling: OpenCV's chessboard search is not bounded there (seconds a frame), with or
  // without the pre-check, since the frames hold a board; the ChArUco board in the same poses
  // for comparison. One iteration each.
  static std::map<std::string, cv::Mat> steep;
  for (const char* spec : {kChessboard, kCharuco}) {
    const Board board(BoardSpec::parse(spec));
    struct Case {
      const char* name;
      double noise, blur, distance, tilt;
    };
    for (const Case& c : {Case{"noise10_blur2_0.9m_tilt60", 10, 2.0, 0.9, 1.05},
                          Case{"noise5_blur0.8_1.8m_tilt60", 5, 0.8, 1.8, 1.05},
                          Case{"noise10_blur0.8_1.8m_tilt34", 10, 0.8, 1.8, 0.6}}) {
      steep[board_kind(spec) + "/" + c.name] =
          render_on_c525(board, c.noise, c.blur, Eigen::Vector3d(0.02, -0.01, c.distance), c.tilt);
    }
  }
  // A board partly out of view under sensor noise (noise 5, blur 0.8 px, on the C525
  // reference, 1280x720): a third or two thirds of the board beyond the image's right edge, the
  // view while the operator brings the board in. OpenCV's quads' search finds no board there and
  // takes seconds; one iteration each. At 1.8 m the chessboard's squares are about 14 px, under
  // what the sector search finds on the 640 px copy: the search image's try runs, on a crop.
  static std::map<std::string, cv::Mat> partial;
  for (const char* spec : {kChessboard, kCharuco}) {
    const Board board(BoardSpec::parse(spec));
    const CameraModel cam = c525_reference_model();
    struct Case {
      const char* name;
      double distance, tilt, out;
    };
    for (const Case& c :
         {Case{"0.45m_third_out", 0.45, 0.0, 0.3}, Case{"0.9m_tilt34_third_out", 0.9, 0.6, 0.3},
          Case{"1.8m_third_out", 1.8, 0.0, 0.3}, Case{"1.8m_two_thirds_out", 1.8, 0.0, 0.7}}) {
      // The board's centre beyond the right edge of the view by `out` of its width less half.
      const double half_view = 0.5 * cam.width() / cam.fx() * c.distance;
      const int squares = board.spec().cols + (board.spec().type == BoardType::kCharuco ? 0 : 1);
      const double width = squares * board.spec().square_length_m;
      const double x = half_view + width * (c.out - 0.5);
      partial[board_kind(spec) + "/" + c.name] =
          render_on_c525(board, 5, 0.8, Eigen::Vector3d(x, 0.02, c.distance), c.tilt);
    }
  }
  // The chessboard with OpenCV's quads' search alone (DetectorOptions::chessboard_sector_search
  // off: the detector before the sector search came first), in the same run.
  DetectorOptions quads_only;
  quads_only.chessboard_sector_search = false;
  for (const auto& [group, frames] :
       {std::pair{"BM_DetectSteep/", &steep}, std::pair{"BM_DetectPartial/", &partial}}) {
    for (const auto& [name, frame] : *frames) {
      const bool chessboard = name.rfind("chessboard", 0) == 0;
      const char* spec = chessboard ? kChessboard : kCharuco;
      for (const bool quads : {false, true}) {
        if (quads && !chessboard) continue;
        benchmark::RegisterBenchmark((group + name + (quads ? "/quads_only" : "")).c_str(),
                                     BM_DetectFrame, std::string(spec), &frame,
                                     quads ? quads_only : DetectorOptions{})
            ->Unit(benchmark::kMillisecond)
            ->MeasureProcessCPUTime()
            ->UseRealTime()
            ->Iterations(1);
      }
    }
  }
  // The chessboard's lattice pre-check (DetectorOptions::chessboard_precheck) off, and the
  // quads' search alone, in the same run: on the scenes, and on the board and noise frames at
  // every size (where the pre-check and the sector search are a cost); the quads' search alone
  // also on the clutter.
  DetectorOptions no_precheck;
  no_precheck.chessboard_precheck = false;
  for (const auto& [variant, options] :
       {std::pair{"/no_precheck", no_precheck}, std::pair{"/quads_only", quads_only}}) {
    for (const auto& [name, frame] : scenes)
      register_frame("BM_DetectScene/chessboard/" + name + variant, kChessboard, &frame, options);
    for (int i = 0; i < static_cast<int>(sizes().size()); ++i) {
      for (const bool noise : {true, false}) {
        register_frame(std::string("BM_Detect/chessboard/") + sizes()[i].name +
                           (noise ? "/noise" : "/board") + variant,
                       kChessboard, &scene(kChessboard, i, noise).image, options);
      }
    }
  }
  for (const auto& [name, frame] : clutter_frames()) {
    if (name.find("_on_") == std::string::npos || name.rfind("chessboard", 0) == 0)
      register_frame("BM_Detect/chessboard/1280x720/" + name + "/quads_only", kChessboard, &frame,
                     quads_only);
  }
  benchmark::Initialize(&argc, argv);
  if (benchmark::ReportUnrecognizedArguments(argc, argv)) return 1;
  benchmark::RunSpecifiedBenchmarks();
  benchmark::Shutdown();
  return 0;
}
