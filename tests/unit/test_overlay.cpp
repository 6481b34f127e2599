// The operator view against reference images (issue 18, item 1; core/select/overlay.cpp): a
// person's session on the synthetic camera, driven through every engine state, its overlay drawn
// on the frame it has just seen and compared, at half size, with tests/data/overlay/*.png.
// POSECAL_UPDATE_OVERLAY_REFERENCES=1 writes the references instead (then look at them); each
// run also leaves what it drew in overlay_actual/ of the working directory.
#include <gtest/gtest.h>

#include <cstdlib>
#include <filesystem>
#include <map>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include "board/views.hpp"
#include "lens/reference_models.hpp"
#include "select/engine.hpp"
#include "sim/sim_camera.hpp"

using namespace posecal;
namespace fs = std::filesystem;

namespace {

const fs::path kReferences = fs::path(POSECAL_SOURCE_DIR) / "tests/data/overlay";

struct Drawn {
  std::map<std::string, cv::Mat> views;  // name -> the half-size overlay
  void take(const std::string& name, const CalibrationEngine& e, const cv::Mat& frame) {
    cv::Mat bgr;
    cv::cvtColor(frame, bgr, cv::COLOR_GRAY2BGR);
    e.draw_overlay(bgr);
    cv::Mat half;
    cv::resize(bgr, half, cv::Size(bgr.cols / 2, bgr.rows / 2), 0, 0, cv::INTER_AREA);
    views[name] = half;
  }
};

// The pose `p` moved by (dx, dy, dz) metres in the camera frame.
Pose shifted(const Pose& p, double dx, double dy, double dz) {
  Pose q = p;
  q.t += Eigen::Vector3d(dx, dy, dz);
  return q;
}

// Frames at `pose` until the engine captures (at most `max_frames`); the frame of the capture.
bool hold(CalibrationEngine& e, SyntheticCamera& cam, const Pose& pose, cv::Mat* captured,
          int max_frames = 10) {
  for (int i = 0; i < max_frames; ++i) {
    const cv::Mat f = cam.render(pose);
    if (e.process(f).captured) {
      *captured = f;
      return true;
    }
  }
  return false;
}

Drawn drive() {
  Drawn d;
  const CameraModel truth = c525_reference_model();
  const Board board;
  SyntheticCamera cam(truth, board, RenderOptions{});
  CalibrationEngine e(truth.size(), EngineOptions{});
  cv::Mat frame(truth.size(), CV_8U, cv::Scalar(110));
  e.process(frame);
  d.take("waiting_for_board", e, frame);
  // A board square to the camera: too weak a view to start from.
  frame = cam.render(board_pose_at(board, Eigen::Vector3d(0, 0, 0.5), 0.0, 0.0, 0.0));
  e.process(frame);
  d.take("bootstrapping", e, frame);
  // A tilted view starts the calibration; the first start pose is shown.
  const Pose start = board_pose_at(board, Eigen::Vector3d(0, 0, 0.5), 0.4, 30 * M_PI / 180, 0.2);
  for (int i = 0; i < 4 && !e.target(); ++i) {
    frame = cam.render(start);
    e.process(frame);
  }
  EXPECT_TRUE(e.target());
  if (!e.target()) return d;
  // The board off to the side and further away than the target: arrow and distance gauge.
  frame = cam.render(shifted(e.target()->T_cam_board, -0.08, 0.03, 0.12));
  e.process(frame);
  d.take("initial_pose_1", e, frame);
  cv::Mat shot;
  EXPECT_TRUE(hold(e, cam, e.target()->T_cam_board, &shot));
  d.take("captured", e, shot);
  frame = cam.render(shifted(e.target()->T_cam_board, 0.06, -0.02, -0.06));
  e.process(frame);
  d.take("initial_pose_2", e, frame);
  for (int guard = 0; guard < 6 && e.state() != EngineState::kRefining; ++guard)
    hold(e, cam, e.target()->T_cam_board, &shot);
  EXPECT_EQ(e.state(), EngineState::kRefining);
  if (!e.target()) return d;
  frame = cam.render(shifted(e.target()->T_cam_board, 0.05, 0.04, 0.0));
  e.process(frame);
  d.take("refining", e, frame);
  for (int guard = 0; guard < 40 && e.target(); ++guard)
    hold(e, cam, e.target()->T_cam_board, &shot);
  EXPECT_EQ(e.state(), EngineState::kConverged) << e.failure_reason();
  d.take("converged", e, shot);
  return d;
}

Drawn drive_to_failure() {
  Drawn d;
  const CameraModel truth = c525_reference_model();
  const Board board;
  SyntheticCamera cam(truth, board, RenderOptions{});
  EngineOptions o;
  o.max_keyframes = 3;
  CalibrationEngine e(truth.size(), o);
  const Pose start = board_pose_at(board, Eigen::Vector3d(0, 0, 0.5), 0.4, 30 * M_PI / 180, 0.2);
  cv::Mat shot;
  for (int i = 0; i < 4 && !e.target(); ++i) e.process(cam.render(start));
  for (int guard = 0; guard < 10 && e.target(); ++guard)
    hold(e, cam, e.target()->T_cam_board, &shot);
  EXPECT_EQ(e.state(), EngineState::kFailed);
  d.take("failed", e, shot);
  return d;
}

}  // namespace

TEST(OperatorView, EveryStateMatchesItsReferenceImage) {
  Drawn d = drive();
  for (auto& [name, view] : drive_to_failure().views) d.views[name] = view;
  const bool update = std::getenv("POSECAL_UPDATE_OVERLAY_REFERENCES") != nullptr;
  fs::create_directories("overlay_actual");
  if (update) fs::create_directories(kReferences);
  for (const char* name : {"waiting_for_board", "bootstrapping", "initial_pose_1", "captured",
                           "initial_pose_2", "refining", "converged", "failed"}) {
    ASSERT_TRUE(d.views.count(name)) << name << " was not reached";
    const cv::Mat& view = d.views[name];
    cv::imwrite("overlay_actual/" + std::string(name) + ".png", view);
    const fs::path ref = kReferences / (std::string(name) + ".png");
    if (update) {
      cv::imwrite(ref.string(), view, {cv::IMWRITE_PNG_COMPRESSION, 9});
      continue;
    }
    const cv::Mat want = cv::imread(ref.string(), cv::IMREAD_COLOR);
    ASSERT_FALSE(want.empty()) << "no reference " << ref;
    ASSERT_EQ(want.size(), view.size()) << name;
    cv::Mat diff, grey;
    cv::absdiff(view, want, diff);
    cv::cvtColor(diff, grey, cv::COLOR_BGR2GRAY);
    const double mean = cv::mean(grey)[0];
    const double far = static_cast<double>(cv::countNonZero(grey > 60)) / grey.total();
    std::printf("%-18s mean difference %.3f, pixels off by > 60: %.4f%%\n", name, mean, 100 * far);
    // Small tolerance: anti-aliased edges that move by a fraction of a pixel with the last bits
    // of a calibration.
    EXPECT_LT(mean, 2.0) << name << ": compare overlay_actual/" << name << ".png with " << ref;
    EXPECT_LT(far, 0.01) << name << ": compare overlay_actual/" << name << ".png with " << ref;
  }
  // Whatever the references say: a captured keyframe frames the image in green, the result
  // screen does not.
  const cv::Vec3b captured = d.views["captured"].at<cv::Vec3b>(180, 1);
  EXPECT_GT(captured[1], 150);
  EXPECT_LT(captured[2], 120);
  const cv::Vec3b result = d.views["converged"].at<cv::Vec3b>(180, 1);
  EXPECT_FALSE(result[1] > 150 && result[2] < 120);
}
