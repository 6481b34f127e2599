// Issue 16, bounded input: one frame costs bounded time whatever its size, one image file is
// checked from its header before it is decoded, and a camera that never shows the board ends its
// session after board_timeout_s.
#include <gtest/gtest.h>
#include <sys/stat.h>
#include <zlib.h>

#include <chrono>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <thread>

#include "board/board.hpp"
#include "board/saddles.hpp"
#include "board/views.hpp"
#include "calib/offline.hpp"
#include "common/error.hpp"
#include "common/image_file.hpp"
#include "device/sources.hpp"
#include "fuzz_frames.hpp"
#include "lens/reference_models.hpp"
#include "session/session.hpp"
#include "sim/clutter.hpp"
#include "sim/synthetic.hpp"

namespace fs = std::filesystem;
using namespace posecal;

namespace {

double seconds_since(std::chrono::steady_clock::time_point t0) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
}

cv::Mat uniform_noise(int width, int height) {
  cv::Mat m(height, width, CV_8U);
  cv::RNG rng(16);
  rng.fill(m, cv::RNG::UNIFORM, 0, 256);
  return m;
}

fs::path fresh_dir(const std::string& name) {
  const fs::path dir = fs::path(testing::TempDir()) / name;
  fs::remove_all(dir);
  fs::create_directories(dir);
  return dir;
}

}  // namespace

// A frame of noise at 12 MP kept the chessboard search busy for > 150 s, and ChArUco's for 10 s
// at 48 MP (issue 16): large frames are searched in a shrunk copy.
TEST(BoundedDetection, LargeNoiseFramesAreSearchedInBoundedTime) {
  const Board chess(BoardSpec::parse("chessboard:9x6:0.025"));
  const Board charuco;
  const cv::Mat noise12 = uniform_noise(4000, 3000), noise48 = uniform_noise(8000, 6000);
  for (const auto& [board, image, name] : {std::tuple{&chess, &noise12, "chessboard 12 MP"},
                                           std::tuple{&chess, &noise48, "chessboard 48 MP"},
                                           std::tuple{&charuco, &noise48, "charuco 48 MP"}}) {
    const auto t0 = std::chrono::steady_clock::now();
    const Detection d = board->detect(*image);
    const double s = seconds_since(t0);
    std::printf("%s of noise: %.3f s, %zu corners\n", name, s, d.size());
    EXPECT_LT(d.size(), 4u) << name;
    EXPECT_LT(s, 3.0) << name;  // measured 0.04-0.09 s CPU; generous for a loaded machine
  }
  // ChArUco's copy of 48 MP of noise, shrunk 7 times, is noise of sigma 10.6, which OpenCV's
  // marker search follows contour by contour (81 ms of CPU): it is searched at 14 (11 ms).
  EXPECT_EQ(charuco.detect(noise48).search_shrink, 14);
}

// Small frames with a striped or checkered pattern gave OpenCV's marker search thousands of
// candidate quads a few pixels around (its minimum perimeter is 3% of the longer side) and took
// 0.6-1.6 s per frame (found by fuzz_session_feed; the patterns are its reproducers' bytes,
// repeated row after row). Quads too small to hold a decodable marker are no longer searched:
// measured 15-19 ms per frame. The bound here only catches a relapse on a loaded machine.
TEST(BoundedDetection, StripedSmallFramesAreSearchedInBoundedTime) {
  const Board charuco;
  const unsigned char pattern[] = {0x3a, 0x04, 0x00, 0x2c, 0x2d, 0x3a, 0x04, 0x2c, 0x00};
  for (const int side : {127, 136, 145, 256}) {
    cv::Mat frame(side, side, CV_8U);
    for (int i = 0; i < side * side; ++i) frame.data[i] = pattern[i % 9];
    const auto t0 = std::chrono::steady_clock::now();
    const Detection d = charuco.detect(frame);
    const double s = seconds_since(t0);
    std::printf("%dx%d striped: %.3f s, %d markers\n", side, side, s, d.markers);
    EXPECT_EQ(d.markers, 0);
    EXPECT_LT(s, 0.4) << side;  // 0.63-1.6 s before (release build)
  }
}

// ... and every marker OpenCV's own rule finds is still found: ChArUco boards with markers of
// 11-16 px (1.8-2.7 px per cell of DICT_4X4) in a 320x240 frame, where 3% of the longer side
// allows quads of 2.4 px a side, give the same markers and corners with and without the minimum.
TEST(BoundedDetection, SmallMarkersInSmallFramesAreStillFound) {
  const CameraModel cam = CameraModel::opencv5(320, 240, 300, 300, 159.5, 119.5, {0, 0, 0, 0, 0});
  const Board board(BoardSpec::parse("charuco:9x6:0.028:0.0182:DICT_4X4_50"));
  RenderOptions ro;
  ro.noise_sigma = 1;
  ro.blur_sigma_px = 0.6;
  SyntheticCamera sc(cam, board, ro);
  DetectorOptions opencv_rule;
  opencv_rule.min_marker_pixels_per_cell = 0;
  int total = 0;
  for (const double z : {0.34, 0.40, 0.45, 0.50}) {  // 300 px * 0.0182 m / z: 16 .. 11 px
    const cv::Mat frame = sc.render(board_pose_at(board, Eigen::Vector3d(0, 0, z), 0.3, 0.1, 0.05));
    const Detection d = board.detect(frame), o = board.detect(frame, opencv_rule);
    std::printf("320x240, markers of %.1f px: %d markers, %zu corners (OpenCV's rule: %d, %zu)\n",
                300 * 0.0182 / z, d.markers, d.size(), o.markers, o.size());
    EXPECT_EQ(d.markers, o.markers) << z;
    EXPECT_EQ(d.ids, o.ids) << z;
    total += d.markers;
  }
  EXPECT_GE(total, 60);  // the scenes do show markers
}

// A chessboard poster, a dot-grid target or a perforated sheet in view gave OpenCV's marker search
// thousands of candidate quads, filtered pairwise (quadratic in their number): 2.4 s for a
// 1280x720 checkerboard of 10 px squares, 1.2 s for a grid of 12 px dots 8 px apart, and
// 64-381 ms for fuzz_session_feed's slow 256x256 dash textures. Above
// DetectorOptions::max_candidate_quads only the largest quads are searched. The bound only
// catches a relapse on a loaded machine; the figures are bench_detection's.
TEST(BoundedDetection, ClutteredFramesAreSearchedInBoundedTime) {
  const Board charuco;
  const cv::Size hd(1280, 720);
  std::vector<std::pair<std::string, cv::Mat>> frames = {
      {"checkerboard 10 px", checkerboard_clutter(hd, 10)},
      {"checkerboard 14 px", checkerboard_clutter(hd, 14)},
      {"dot grid 12/8 px", dot_grid_clutter(hd, 12, 8)},
      {"dot grid 16/8 px", dot_grid_clutter(hd, 16, 8)}};
  const fs::path slow = fs::path(POSECAL_SOURCE_DIR) / "tests/fuzz/crashes/fuzz_session_feed";
  for (const auto& entry : fs::directory_iterator(slow)) {
    const std::string name = entry.path().filename().string();
    if (name.rfind("slow-", 0) == 0)
      frames.emplace_back(name, testing_support::fuzz_session_frame(entry.path().string()));
  }
  ASSERT_GE(frames.size(), 8u);
  for (const auto& [name, frame] : frames) {
    ASSERT_FALSE(frame.empty()) << name;
    const auto t0 = std::chrono::steady_clock::now();
    const Detection d = charuco.detect(frame);
    const double s = seconds_since(t0);
    std::printf("%s (%dx%d): %.3f s, %d markers\n", name.c_str(), frame.cols, frame.rows, s,
                d.markers);
    EXPECT_EQ(d.markers, 0) << name;
    EXPECT_LT(s, 0.5) << name;  // 0.06-2.4 s before (release build)
  }
}

// ... and a board in front of the clutter is found as OpenCV's uncapped search finds it: the same
// markers and corners, its markers (about 40 px) being larger than the clutter's quads. Such a
// frame is busy (more blobs than the cap), so its markers are searched on a half-size copy; the
// corners, refined at full resolution, agree with the full-resolution search's to 0.01 px.
TEST(BoundedDetection, ABoardInFrontOfClutterIsStillFound) {
  const CameraModel cam = c525_reference_model();
  const Board board;
  RenderOptions ro;
  ro.blur_sigma_px = 0.8;
  SyntheticCamera sc(cam, board, ro);
  const Pose pose = board_pose_at(board, Eigen::Vector3d(0.01, 0.005, 0.48), 0.5, 0.35, 0.1);
  const auto truth = sc.true_corners(pose);
  DetectorOptions uncapped;
  uncapped.max_candidate_quads = 0;
  for (const auto& [name, background] :
       {std::pair{"checkerboard 10 px", checkerboard_clutter(cam.size(), 10)},
        std::pair{"dot grid 12/8 px", dot_grid_clutter(cam.size(), 12, 8)}}) {
    const cv::Mat frame = render_in_front_of(sc, pose, background);
    const auto t0 = std::chrono::steady_clock::now();
    const Detection d = board.detect(frame);
    const double s = seconds_since(t0);
    const Detection o = board.detect(frame, uncapped);
    double ss = 0;
    for (size_t i = 0; i < d.size(); ++i)
      ss += std::pow(cv::norm(d.image_points[i] - truth[d.ids[i]]), 2);
    std::printf("board in front of a %s: %.3f s, %d markers, %zu corners, rms %.4f px\n", name, s,
                d.markers, d.size(), d.empty() ? 0.0 : std::sqrt(ss / d.size()));
    EXPECT_EQ(d.markers, (board.spec().cols * board.spec().rows) / 2) << name;
    EXPECT_EQ(d.size(), static_cast<size_t>(board.num_corners())) << name;
    EXPECT_EQ(d.markers, o.markers) << name;
    EXPECT_EQ(d.ids, o.ids) << name;
    for (size_t i = 0; i < std::min(d.size(), o.size()); ++i)
      EXPECT_LT(cv::norm(d.image_points[i] - o.image_points[i]), 0.01) << name << " corner " << i;
    EXPECT_LT(std::sqrt(ss / std::max<size_t>(1, d.size())), 0.1) << name;
    EXPECT_LT(s, 0.5) << name;
  }
}

// Frames without clutter, boards and noise, give OpenCV's detection bit for bit: the cap changes
// nothing below it.
TEST(BoundedDetection, FramesWithoutClutterAreUnchangedByTheCandidateCap) {
  const CameraModel cam = c525_reference_model();
  DetectorOptions uncapped;
  uncapped.max_candidate_quads = 0;
  for (const std::string spec : {"charuco:9x6:0.028:0.0182:DICT_4X4_50", "chessboard:9x6:0.025"}) {
    const Board board(BoardSpec::parse(spec));
    RenderOptions ro;
    ro.noise_sigma = 5;  // sensor noise of a dim scene
    SyntheticCamera sc(cam, board, ro);
    std::vector<cv::Mat> frames;
    if (board.spec().type == BoardType::kCharuco) {  // noise is the chessboard's cluttered frame
      frames = {uniform_noise(1280, 720), uniform_noise(640, 480), uniform_noise(256, 256)};
    }
    for (const Pose& p : random_board_views(11, 4, cam, board)) frames.push_back(sc.render(p));
    if (board.spec().type == BoardType::kCharuco) {
      // Sensor noise of sigma 15 gives a ChArUco board frame 276-453 busy blobs: under twice the
      // cap, so these keep the full-resolution search (and every corner it finds).
      RenderOptions noisy = ro;
      noisy.noise_sigma = 15;
      SyntheticCamera nc(cam, board, noisy);
      for (const Pose& p : random_board_views(12, 2, cam, board)) frames.push_back(nc.render(p));
    }
    for (const cv::Mat& img : frames) {
      const Detection a = board.detect(img), b = board.detect(img, uncapped);
      EXPECT_EQ(a.markers, b.markers) << spec;
      EXPECT_EQ(a.ids, b.ids) << spec;
      EXPECT_EQ(a.image_points, b.image_points) << spec;  // bit-identical
    }
  }
}

// The chessboard's cluttered frames: uniform noise (1.4 s before at 1280x720) and checkerboard
// textures (14 px squares: 5.3 s) are searched on a half-size copy; a chessboard in front of a
// texture is found there and refined at full resolution, as a large frame's. The bound only
// catches a relapse.
TEST(BoundedDetection, ChessboardSearchesOfClutterAreBounded) {
  const CameraModel cam = c525_reference_model();
  const Board board(BoardSpec::parse("chessboard:9x6:0.025"));
  for (const auto& [name, frame] :
       {std::pair{"uniform noise", uniform_noise(1280, 720)},
        std::pair{"checkerboard 14 px", checkerboard_clutter(cam.size(), 14)},
        std::pair{"checkerboard 20 px", checkerboard_clutter(cam.size(), 20)}}) {
    const auto t0 = std::chrono::steady_clock::now();
    const Detection d = board.detect(frame);
    const double s = seconds_since(t0);
    std::printf("chessboard search of %s: %.3f s, %zu corners\n", name, s, d.size());
    EXPECT_TRUE(d.empty()) << name;
    EXPECT_LT(s, 0.5) << name;
  }
  RenderOptions ro;
  ro.blur_sigma_px = 0.8;
  SyntheticCamera sc(cam, board, ro);
  // Board squares of about 54, 40 and 32 px: the first found at quarter size, the others at half
  // size, on the copy with the clutter closed (12-20 ms; among the clutter's quads 190-330 ms;
  // docs/performance.md, "Busy frames"), as accurate as before (0.028-0.046 px).
  for (const double distance : {0.5, 0.68, 0.85}) {
    const Pose pose = board_pose_at(board, Eigen::Vector3d(0.01, 0.005, distance), 0.5, 0.35, 0.1);
    const auto truth = sc.true_corners(pose);
    for (const int square : {10, 14}) {
      const cv::Mat frame = render_in_front_of(sc, pose, checkerboard_clutter(cam.size(), square));
      const Detection d = board.detect(frame);
      ASSERT_EQ(d.size(), static_cast<size_t>(board.num_corners())) << square << " " << distance;
      double ss = 0;
      for (size_t i = 0; i < d.size(); ++i)
        ss += std::pow(cv::norm(d.image_points[i] - truth[d.ids[i]]), 2);
      std::printf("chessboard at %.2f m in front of a %d px checkerboard: rms %.4f px\n", distance,
                  square, std::sqrt(ss / d.size()));
      EXPECT_LT(std::sqrt(ss / d.size()), 0.1) << square << " " << distance;
    }
  }
}

// Scenes without a board kept OpenCV's chessboard search busy for 0.1-1.9 s a frame (a circuit
// board, fruit and a painting at 1280 px; docs/performance.md, "Scenes without a board"): the
// lattice pre-check (board/saddles.hpp) finds too few chessboard crossings in them, so the
// search does not run.
TEST(BoundedDetection, ScenesWithoutABoardAreRejectedBeforeTheChessboardSearch) {
  const fs::path data = "/usr/share/doc/opencv-doc/examples/data";
  if (!fs::exists(data / "board.jpg")) GTEST_SKIP() << "Debian's opencv-doc is not installed";
  const Board board(BoardSpec::parse("chessboard:9x6:0.025"));
  const int needed = chessboard_crossings_needed(9, 6);
  EXPECT_EQ(needed, 7);
  for (const char* file : {"board.jpg", "apple.jpg", "pic2.png", "aero3.jpg", "home.jpg"}) {
    const cv::Mat image = cv::imread((data / file).string(), cv::IMREAD_GRAYSCALE);
    ASSERT_FALSE(image.empty()) << file;
    cv::Mat large;
    const double s = 1280.0 / std::max(image.cols, image.rows);
    cv::resize(image, large, cv::Size(), s, s, cv::INTER_CUBIC);
    for (const cv::Mat& frame : {image, large}) {
      const int crossings = chessboard_crossings(frame);
      std::printf("%s at %dx%d: %d crossings\n", file, frame.cols, frame.rows, crossings);
      EXPECT_LT(crossings, needed) << file << " at " << frame.cols << " px";
      EXPECT_TRUE(board.detect(frame).empty()) << file;
    }
  }
  // A checkerboard texture is a lattice: it is searched (ChessboardSearchesOfClutterAreBounded
  // bounds that search), however few of its saddles the cap keeps.
  EXPECT_GE(chessboard_crossings(checkerboard_clutter(cv::Size(1280, 720), 14)), needed);
  // So is a frame too small to examine (a tracked region of a few squares).
  EXPECT_EQ(chessboard_crossings(checkerboard_clutter(cv::Size(200, 40), 4)), kCannotTell);
  EXPECT_EQ(chessboard_crossings(cv::Mat(90, 1400, CV_8U, cv::Scalar(128))), kCannotTell);
}

// The pre-check loses no board that OpenCV's quads' search finds: OpenCV's 26 photos of a 9x6
// board (640x480, and scaled up to 1280 px), and rendered boards near and far, tilted up to 35
// degrees, blurred and noisy, of 8-60 px squares, give the same corners with and without it.
// (Boards tilted 60 degrees cost the quads' search 2-26 s a frame at 1280x720 with or without
// the pre-check: docs/performance.md, "Steep boards under noise".)
//
// And the detector as it is, the sector search alone on frames that are not busy
// (DetectorOptions::chessboard_sector_search), finds each of these boards too, its corners in
// the same order, within 0.01 px after the refinement in all but 4 of the frames: the refinement
// starts from the other search's corners. On a blurred photo (left13.jpg) and a rendered board of
// 15 px squares under noise 10 and blur 2 px they end up to 0.7 px apart (the rendered one 0.28
// px RMS from the true corners now, 0.47 px before); on two photos found only with the histogram
// equalised (right01.jpg, right04.jpg), 0.04-0.1 px (the calibration on the 13 right photos:
// RMS 0.2774 px, 0.2776 with the quads' search). (It also finds boards the pre-check turns away
// before the quads' search, which cannot find them: 8 px squares tilted 35 degrees give 4
// crossings.)
TEST(BoundedDetection, TheChessboardPrecheckKeepsEveryBoard) {
  const Board board(BoardSpec::parse("chessboard:9x6:0.025"));
  DetectorOptions quads_only;  // the pre-check, then the quads' search alone
  quads_only.chessboard_sector_search = false;
  DetectorOptions without = quads_only;  // the quads' search alone
  without.chessboard_precheck = false;
  int compared = 0;
  int apart = 0;  // frames with a corner more than 0.01 px from the quads' search alone
  auto same = [&](const cv::Mat& frame, const std::string& name) {
    const Detection q = board.detect(frame, quads_only);
    const Detection o = board.detect(frame, without);
    if (o.empty()) return;
    ++compared;
    const int crossings = chessboard_crossings(frame);
    EXPECT_EQ(q.ids, o.ids) << name << ": " << crossings << " crossings";
    for (size_t i = 0; i < std::min(q.size(), o.size()); ++i)
      EXPECT_EQ(q.image_points[i], o.image_points[i]) << name << " corner " << i;
    // The detector as it is: the sector search alone.
    const Detection d = board.detect(frame);
    EXPECT_EQ(d.ids, o.ids) << name << ": the sector search";
    double worst = 0;
    for (size_t i = 0; i < std::min(d.size(), o.size()); ++i)
      worst = std::max(worst, cv::norm(d.image_points[i] - o.image_points[i]));
    EXPECT_LT(worst, 1.0) << name;  // numbered alike: a corner further off is another corner
    if (worst > 0.01) {
      std::printf("%s: up to %.3f px from the quads' search alone\n", name.c_str(), worst);
      ++apart;
    }
  };
  const fs::path data = "/usr/share/doc/opencv-doc/examples/data";
  for (const char* side : {"left", "right"}) {
    for (int i = 1; i <= 14; ++i) {
      char file[32];
      std::snprintf(file, sizeof file, "%s%02d.jpg", side, i);
      const cv::Mat image = cv::imread((data / file).string(), cv::IMREAD_GRAYSCALE);
      if (image.empty()) continue;
      cv::Mat large;
      cv::resize(image, large, cv::Size(1280, 960), 0, 0, cv::INTER_CUBIC);
      same(image, file);
      same(large, std::string(file) + "@1280");
    }
  }
  const CameraModel cam = c525_reference_model();
  int rendered = 0;
  for (const double noise : {2.0, 10.0}) {
    for (const double blur : {0.8, 2.0}) {
      RenderOptions ro;
      ro.blur_sigma_px = blur;
      ro.noise_sigma = noise;
      ro.supersample = 1;
      SyntheticCamera sc(cam, board, ro);
      // Squares of about 60, 30, 15 and 8 px.
      for (const double distance : {0.45, 0.9, 1.8, 3.2}) {
        for (const double tilt : {0.0, 0.6}) {
          const Pose p =
              board_pose_at(board, Eigen::Vector3d(0.02, -0.01, distance), 0.4, tilt, 0.3);
          char name[96];
          std::snprintf(name, sizeof name, "rendered: noise %.0f, blur %.1f, %.2f m, tilt %.2f",
                        noise, blur, distance, tilt);
          const int before = compared;
          same(sc.render(p), name);
          rendered += compared - before;
        }
      }
    }
  }
  std::printf("%d frames where OpenCV finds the board, %d of them rendered\n", compared, rendered);
  EXPECT_LE(apart, 4);
  EXPECT_GE(compared, 60);
  EXPECT_GE(rendered, 20);
}

// A chessboard tilted 60 degrees under sensor noise kept OpenCV's quads' search busy for 8-20 s a
// frame at 1280x720 without finding the board (docs/performance.md, "Steep boards under noise");
// the sector search, which runs first, finds it, the corners refined as any others. (Found
// here, the frame did not reach the quads' search: it cannot find these boards.)
TEST(BoundedDetection, SteepNoisyChessboardsAreFoundBySectors) {
  const CameraModel cam = c525_reference_model();
  const Board board(BoardSpec::parse("chessboard:9x6:0.025"));
  struct Case {
    double noise, blur, distance;
  };
  for (const Case& c : {Case{10, 2.0, 0.9}, Case{5, 0.8, 1.8}, Case{10, 0.8, 1.8}}) {
    RenderOptions ro;
    ro.noise_sigma = c.noise;
    ro.blur_sigma_px = c.blur;
    ro.supersample = 1;
    SyntheticCamera sc(cam, board, ro);
    const Pose pose =
        board_pose_at(board, Eigen::Vector3d(0.02, -0.01, c.distance), 0.4, 1.05, 0.3);
    const Detection d = board.detect(sc.render(pose));
    ASSERT_EQ(d.size(), static_cast<size_t>(board.num_corners())) << c.noise << " " << c.distance;
    const auto truth = sc.true_corners(pose);
    double ss = 0;
    for (size_t i = 0; i < d.size(); ++i)
      ss += std::pow(cv::norm(d.image_points[i] - truth[d.ids[i]]), 2);
    std::printf("noise %.0f, blur %.1f, %.1f m, tilted 60 degrees: rms %.3f px\n", c.noise, c.blur,
                c.distance, std::sqrt(ss / d.size()));
    EXPECT_LT(std::sqrt(ss / d.size()), 0.3) << c.noise << " " << c.distance;
  }
}

// The pre-check's lattice measures the board's squares (chessboard_lattice's spacing), from
// which the detector decides whether the sector search at full resolution is needed (boards of
// 6-12 px squares at 1280x720 were found only there, none of 16 px or more). Rendered boards of
// about 60, 30, 15 and 9 px squares, facing the camera and tilted 52 degrees (the shorter side
// foreshortened to 0.62 of it), are each measured within 10% of their shorter square side, and
// each is found: those of 9 px squares at 1.8 and 3 m on a crop about the crossings, that of 5.7
// px squares in the whole frame. (With the saddles at whole pixels, the board at 3 m facing the
// camera gave 2 crossings and was turned away by the pre-check.)
TEST(BoundedDetection, TheLatticeMeasuresTheSquares) {
  const CameraModel cam = c525_reference_model();
  const Board board(BoardSpec::parse("chessboard:9x6:0.025"));
  RenderOptions ro;
  ro.noise_sigma = 5;
  ro.blur_sigma_px = 0.8;
  ro.supersample = 1;
  SyntheticCamera sc(cam, board, ro);
  for (const double distance : {0.45, 0.9, 1.8, 3.0}) {
    for (const double tilt : {0.0, 0.9}) {
      const Pose pose = board_pose_at(board, Eigen::Vector3d(0.02, -0.01, distance), 0.0, tilt, 0);
      const cv::Mat frame = sc.render(pose);
      const double square = cam.fx() * 0.025 / distance * std::cos(tilt);
      const ChessboardLattice lattice = chessboard_lattice(frame);
      std::printf("%.2f m, tilt %.1f: squares of %.1f px, lattice spacing %.1f px (%d crossings)\n",
                  distance, tilt, square, lattice.spacing_px, lattice.crossings);
      EXPECT_NEAR(lattice.spacing_px, square, 0.1 * square) << distance << " m, tilt " << tilt;
      EXPECT_EQ(board.detect(frame).size(), static_cast<size_t>(board.num_corners()))
          << distance << " m, tilt " << tilt;
    }
  }
  // Nothing to measure: a flat frame, and one too small to examine.
  EXPECT_EQ(chessboard_lattice(cv::Mat(720, 1280, CV_8U, cv::Scalar(128))).spacing_px, 0);
  EXPECT_EQ(chessboard_lattice(cv::Mat(40, 200, CV_8U, cv::Scalar(128))).spacing_px, 0);
}

// Above DetectorOptions::search_max_side the frame is searched on a shrunk copy, and the pre-check
// examined that copy at half size again: a 1920x1080 frame at a quarter of its resolution, where a
// board of 11-14 px squares gave 0-16 crossings and was turned away although OpenCV's sector
// search finds it (7 of 41 boards, docs/performance.md, "Boards partly out of view"). The copy is
// now examined as it is.
TEST(BoundedDetection, ThePrecheckKeepsSmallSquaresOfLargeFrames) {
  const Board board(BoardSpec::parse("chessboard:9x6:0.025"));
  const CameraModel cam =
      CameraModel::opencv5(1920, 1080, 1500, 1500, 955, 545, {-0.08, 0.05, 0.0005, -0.0003, 0});
  RenderOptions ro;
  ro.noise_sigma = 3;
  ro.blur_sigma_px = 1.0;
  ro.supersample = 1;
  SyntheticCamera sc(cam, board, ro);
  struct Case {
    double square_px, tilt;
  };
  for (const Case& c : {Case{11.0, 0.2}, Case{13.5, 0.7}}) {
    const double distance = cam.fx() * 0.025 / c.square_px;
    const Pose pose =
        board_pose_at(board, Eigen::Vector3d(-0.03, 0.015, distance), 1.2, c.tilt, -0.5);
    const Detection d = board.detect(sc.render(pose));
    EXPECT_EQ(d.size(), static_cast<size_t>(board.num_corners()))
        << c.square_px << " px squares, tilt " << c.tilt;
  }
}

// The two searches number a board's corners alike: boards of 9x6, 6x9, 8x6 and 7x5 inner corners
// in 16 poses each (turned about the view axis by up to a quarter turn either way), where the
// quads' search finds them. A board of odd x odd corners is the same after a half turn, and the
// quads' search has no rule for which of its two orders it gives: there the orders may be each
// other's reverse (the 7x5 board turned a quarter turn, once).
TEST(BoundedDetection, TheSectorSearchNumbersCornersAsTheQuadsSearch) {
  const CameraModel cam = c525_reference_model();
  DetectorOptions quads_only;
  quads_only.chessboard_sector_search = false;
  for (const char* spec : {"chessboard:9x6:0.025", "chessboard:6x9:0.025", "chessboard:8x6:0.025",
                           "chessboard:7x5:0.03"}) {
    const Board board(BoardSpec::parse(spec));
    RenderOptions ro;
    ro.noise_sigma = 2;
    SyntheticCamera sc(cam, board, ro);
    int compared = 0;
    for (int i = 0; i < 16; ++i) {
      const double roll = -1.6 + 3.2 * i / 15.0;
      const Pose pose =
          board_pose_at(board, Eigen::Vector3d(0.01 * (i % 3), -0.01, 0.55 + 0.05 * (i % 4)),
                        0.3 * i, 0.2 + 0.03 * i, roll);
      const cv::Mat frame = sc.render(pose);
      const Detection q = board.detect(frame, quads_only);
      if (q.empty()) continue;
      ++compared;
      const Detection d = board.detect(frame);
      ASSERT_EQ(d.ids, q.ids) << spec << " pose " << i;
      const bool symmetric = board.spec().cols % 2 == 1 && board.spec().rows % 2 == 1;
      const bool reversed =
          symmetric && cv::norm(d.image_points.front() - q.image_points.back()) < 1.0;
      for (size_t j = 0; j < d.size(); ++j) {
        const cv::Point2d other = q.image_points[reversed ? d.size() - 1 - j : j];
        EXPECT_LT(cv::norm(d.image_points[j] - other), 0.01)
            << spec << " pose " << i << " corner " << j;
      }
    }
    std::printf("%s: %d poses compared\n", spec, compared);
    EXPECT_GE(compared, 10) << spec;
  }
}

// The corners of a large frame are refined at full resolution: at 12 MP they are as accurate as
// at 1280x720 (SyntheticCamera.DetectedCornersMatchTrueProjections: < 0.1 px RMS, < 0.3 px).
TEST(BoundedDetection, LargeFramesKeepTheirCornerAccuracy) {
  const double f = 3200;
  const CameraModel cam =
      CameraModel::opencv5(4000, 3000, f, f, 1999.5, 1499.5, {0.05, -0.02, 0, 0, 0});
  for (const std::string spec : {"chessboard:9x6:0.025", "charuco:9x6:0.028:0.0182:DICT_4X4_50"}) {
    const Board board(BoardSpec::parse(spec));
    RenderOptions ro;
    ro.supersample = 1;
    ro.noise_sigma = 2;
    ro.blur_sigma_px = 1.5;
    SyntheticCamera sc(cam, board, ro);
    for (const double tilt : {0.6}) {
      const Pose p = board_pose_at(board, Eigen::Vector3d(0.02, 0.01, 0.45), 0.6, tilt, 0.2);
      const Detection d = board.detect(sc.render(p));
      ASSERT_EQ(d.size(), static_cast<size_t>(board.num_corners())) << spec << " tilt " << tilt;
      // A camera's frame is not a noisy copy: the markers are searched at the size's factor.
      if (board.spec().type == BoardType::kCharuco) {
        EXPECT_EQ(d.search_shrink, 4) << spec;
      }
      const auto truth = sc.true_corners(p);
      double ss = 0, worst = 0;
      for (size_t i = 0; i < d.size(); ++i) {
        const double e = cv::norm(d.image_points[i] - truth[d.ids[i]]);
        ss += e * e;
        worst = std::max(worst, e);
      }
      const double rms = std::sqrt(ss / d.size());
      std::printf("%s at 12 MP, tilt %.1f: rms %.4f px, worst %.4f px\n", spec.c_str(), tilt, rms,
                  worst);
      EXPECT_LT(rms, 0.1) << spec;
      EXPECT_LT(worst, 0.3) << spec;
    }
  }
}

// Frames up to DetectorOptions::kSearchMaxSide (1280x720 and below, the sizes in use) take the
// full-resolution path: the same corners as with the shrunk search turned off.
TEST(BoundedDetection, FramesUpToTheSearchSizeTakeTheFullResolutionPath) {
  ASSERT_GE(DetectorOptions::kSearchMaxSide, 1280);
  const CameraModel cam = c525_reference_model();
  DetectorOptions full;
  full.search_max_side = 0;
  for (const std::string spec : {"chessboard:9x6:0.025", "charuco:9x6:0.028:0.0182:DICT_4X4_50"}) {
    const Board board(BoardSpec::parse(spec));
    SyntheticCamera sc(cam, board);
    for (const Pose& p : random_board_views(7, 3, cam, board)) {
      const cv::Mat img = sc.render(p);
      const Detection a = board.detect(img), b = board.detect(img, full);
      ASSERT_FALSE(a.empty()) << spec;
      EXPECT_EQ(a.ids, b.ids) << spec;
      EXPECT_EQ(a.image_points, b.image_points) << spec;  // bit-identical
    }
  }
}

TEST(BoundedDetection, FramesAboveTheLimitAreRefusedNamingIt) {
  const Board board;
  const cv::Mat huge(12000, 9000, CV_8U);  // 108 MP, never touched
  try {
    board.detect(huge);
    ADD_FAILURE() << "a 108 MP frame was searched";
  } catch (const Error& e) {
    EXPECT_EQ(e.code(), ErrorCode::kInvalidArgument);
    EXPECT_NE(std::string(e.what()).find("kMaxDetectPixels"), std::string::npos) << e.what();
    EXPECT_NE(std::string(e.what()).find("100 megapixels"), std::string::npos) << e.what();
  }
}

namespace {

void put_be32(std::string* s, uint32_t v) {
  for (int shift : {24, 16, 8, 0}) s->push_back(static_cast<char>((v >> shift) & 0xFF));
}

void put_chunk(std::ofstream& out, const char* type, const std::string& data) {
  std::string c;
  put_be32(&c, static_cast<uint32_t>(data.size()));
  const std::string body = std::string(type, 4) + data;
  uLong crc = crc32(0, reinterpret_cast<const Bytef*>(body.data()), static_cast<uInt>(body.size()));
  c += body;
  put_be32(&c, static_cast<uint32_t>(crc));
  out.write(c.data(), static_cast<std::streamsize>(c.size()));
}

// A valid black 1-bit PNG of `side` x `side`, compressed row by row (a few hundred KB for 20000).
void write_black_png(const fs::path& path, int side) {
  std::ofstream out(path, std::ios::binary);
  out.write("\x89PNG\r\n\x1a\n", 8);
  std::string ihdr;
  put_be32(&ihdr, static_cast<uint32_t>(side));
  put_be32(&ihdr, static_cast<uint32_t>(side));
  ihdr += std::string("\x01\x00\x00\x00\x00", 5);  // 1 bit, grey, deflate, no filter, no interlace
  put_chunk(out, "IHDR", ihdr);
  z_stream z{};
  ASSERT_EQ(deflateInit(&z, 9), Z_OK);
  const std::string row(1 + (side + 7) / 8, '\0');  // filter byte + the row's bits
  std::string compressed;
  std::vector<unsigned char> buf(1 << 16);
  for (int r = 0; r <= side; ++r) {
    const bool last = r == side;
    z.next_in = reinterpret_cast<Bytef*>(const_cast<char*>(row.data()));
    z.avail_in = last ? 0 : static_cast<uInt>(row.size());
    do {
      z.next_out = buf.data();
      z.avail_out = static_cast<uInt>(buf.size());
      deflate(&z, last ? Z_FINISH : Z_NO_FLUSH);
      compressed.append(reinterpret_cast<char*>(buf.data()), buf.size() - z.avail_out);
    } while (z.avail_out == 0);
  }
  deflateEnd(&z);
  put_chunk(out, "IDAT", compressed);
  put_chunk(out, "IEND", "");
}

}  // namespace

// The header reader agrees with the encoders on every format it knows.
TEST(BoundedImageFile, HeadersGiveTheDimensionsOfEveryFormat) {
  const fs::path dir = fresh_dir("posecal_bounded_formats");
  const cv::Mat img = uniform_noise(37, 23);
  for (const std::string ext : {".png", ".jpg", ".bmp", ".pgm", ".pam", ".tif", ".webp", ".ras"}) {
    const fs::path file = dir / ("img" + ext);
    ASSERT_TRUE(cv::imwrite(file.string(), img)) << ext;
    const ImageFileInfo info = check_image_file(file.string());
    EXPECT_EQ(info.width, 37) << ext << " " << info.format;
    EXPECT_EQ(info.height, 23) << ext << " " << info.format;
  }
  std::ofstream(dir / "notes.txt") << "not an image";
  try {
    check_image_file((dir / "notes.txt").string());
    ADD_FAILURE() << "a text file passed as an image";
  } catch (const Error& e) {
    EXPECT_EQ(e.code(), ErrorCode::kUnsupported);
    EXPECT_NE(std::string(e.what()).find("not a readable image"), std::string::npos) << e.what();
  }
  std::ofstream(dir / "cut.png", std::ios::binary) << "\x89PNG\r\n\x1a\n";
  EXPECT_THROW(check_image_file((dir / "cut.png").string()), Error);
}

// A 20000 x 20000 black PNG of a few hundred KB took 99.5 s and 2.4 GB to decode from an images
// folder (issue 16); offline calibration now lists it as rejected, naming the limit.
TEST(BoundedImageFile, AHugeImageIsRejectedFromItsHeaderNamingTheLimit) {
  const fs::path dir = fresh_dir("posecal_bounded_huge");
  const CameraModel cam = c525_reference_model();
  const Board board;
  SyntheticCamera sc(cam, board);
  int n = 0;
  for (const Pose& p : random_board_views(3, 4, cam, board))
    cv::imwrite((dir / ("frame" + std::to_string(n++) + ".png")).string(), sc.render(p));
  write_black_png(dir / "huge.png", 20000);
  EXPECT_LT(fs::file_size(dir / "huge.png"), 2'000'000u);
  const auto t0 = std::chrono::steady_clock::now();
  const OfflineCalibration cal = calibrate_images(dir.string(), board.spec());
  EXPECT_LT(seconds_since(t0), 20.0);
  EXPECT_EQ(cal.used.size(), 4u);
  ASSERT_EQ(cal.rejected.size(), 1u);
  EXPECT_EQ(cal.rejected[0].file, "huge.png");
  EXPECT_NE(cal.rejected[0].reason.find("20000x20000"), std::string::npos)
      << cal.rejected[0].reason;
  EXPECT_NE(cal.rejected[0].reason.find("limit of 50.0 MP"), std::string::npos)
      << cal.rejected[0].reason;

  // images://: skipped as incomplete, the stream goes on to its end at once.
  auto cam_dev = make_images_backend()->open(Uri::parse("images://" + dir.string()));
  cam_dev->configure({});
  cam_dev->start();
  Frame f;
  int frames = 0;
  while (cam_dev->next_frame(100, &f) == FrameStatus::kOk) ++frames;
  EXPECT_EQ(frames, 4);
  EXPECT_EQ(cam_dev->stats().frames_incomplete, 1u);
}

// A FIFO is refused without blocking (opened with O_NONBLOCK; nobody ever writes to it).
TEST(BoundedImageFile, AFifoIsRefusedWithoutBlocking) {
  const fs::path dir = fresh_dir("posecal_bounded_fifo");
  const fs::path fifo = dir / "pipe.png";
  ASSERT_EQ(mkfifo(fifo.c_str(), 0600), 0);
  try {
    read_grey_image(fifo.string());
    ADD_FAILURE() << "a FIFO was read";
  } catch (const Error& e) {
    EXPECT_EQ(e.code(), ErrorCode::kInvalidArgument);
    EXPECT_NE(std::string(e.what()).find("FIFO"), std::string::npos) << e.what();
  }
  EXPECT_THROW(calibrate_images(dir.string(), BoardSpec{}), Error);  // no image: kDegenerate
}

namespace {

std::unique_ptr<CalibrationSession> external_session(double board_timeout_s) {
  EngineOptions o;
  o.board_timeout_s = board_timeout_s;
  auto cam = make_external_backend()->open(Uri::parse("external"));
  return std::make_unique<CalibrationSession>(std::move(cam), o);
}

// Feeds `frame` every 10 ms until the session finishes or `seconds` pass; the seconds it ran.
double feed_for(CalibrationSession* s, const cv::Mat& frame, double seconds) {
  const auto t0 = std::chrono::steady_clock::now();
  while (!s->finished() && seconds_since(t0) < seconds) {
    s->feed(frame);
    std::this_thread::sleep_for(std::chrono::milliseconds(10));
  }
  return seconds_since(t0);
}

}  // namespace

// A camera that never shows the board held a station for its whole max_seconds (1800 s): the
// session now fails after board_timeout_s, saying why.
TEST(BoundedSession, BlankFramesEndTheSessionAfterTheBoardTimeout) {
  auto s = external_session(0.3);
  const double ran = feed_for(s.get(), cv::Mat(480, 640, CV_8U, cv::Scalar(128)), 10.0);
  ASSERT_TRUE(s->finished());
  EXPECT_GE(ran, 0.3);
  EXPECT_LT(ran, 5.0);
  EXPECT_EQ(s->engine().state(), EngineState::kFailed);
  EXPECT_FALSE(s->engine().converged());
  const std::string why = s->engine().failure_reason();
  EXPECT_NE(why.find("no board"), std::string::npos) << why;
  EXPECT_NE(why.find("board_timeout_s = 0.3"), std::string::npos) << why;
  EXPECT_THROW(s->feed(cv::Mat(480, 640, CV_8U, cv::Scalar(128))), Error);  // finished
}

// A started camera that never delivers a frame (the engine is made at the first frame) held the
// session until the host's own limit: it now ends after board_timeout_s as well, saying so.
TEST(BoundedSession, ACameraWithoutFramesEndsTheSessionAfterTheBoardTimeout) {
  auto s = external_session(0.3);  // the external camera delivers nothing unless fed
  const auto t0 = std::chrono::steady_clock::now();
  StepStatus last = StepStatus::kTimeout;
  while (seconds_since(t0) < 10.0 && last == StepStatus::kTimeout) last = s->step(20);
  const double ran = seconds_since(t0);
  EXPECT_EQ(last, StepStatus::kFinished);
  ASSERT_TRUE(s->finished());
  EXPECT_GE(ran, 0.3);
  EXPECT_LT(ran, 5.0);
  EXPECT_FALSE(s->has_engine());
  const std::string why = s->no_frame_failure();
  EXPECT_NE(why.find("no frame from the camera"), std::string::npos) << why;
  EXPECT_NE(why.find("board_timeout_s = 0.3"), std::string::npos) << why;
  EXPECT_THROW(s->feed(cv::Mat(480, 640, CV_8U, cv::Scalar(128))), Error);  // finished
  auto never = external_session(0);  // 0: no limit
  const auto t1 = std::chrono::steady_clock::now();
  while (seconds_since(t1) < 0.6) ASSERT_EQ(never->step(20), StepStatus::kTimeout);
  EXPECT_FALSE(never->finished());
}

TEST(BoundedSession, ABoardInViewOrATimeoutOfZeroKeepsTheSessionGoing) {
  const CameraModel cam = c525_reference_model();
  const Board board;
  SyntheticCamera sc(cam, board);
  const cv::Mat frame = sc.render(random_board_views(3, 1, cam, board)[0]);
  auto seen = external_session(0.3);
  feed_for(seen.get(), frame, 0.8);
  EXPECT_FALSE(seen->finished()) << seen->engine().failure_reason();
  auto never = external_session(0);
  feed_for(never.get(), cv::Mat(720, 1280, CV_8U, cv::Scalar(128)), 0.6);
  EXPECT_FALSE(never->finished());
}
