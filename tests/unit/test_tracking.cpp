// Tracking the board between frames (core/board/tracking.hpp): a tracked search finds what the
// whole-frame search finds, falls back to it when the board left the region, and the engine's
// keyframes are whole-frame searches.
#include <gtest/gtest.h>

#include <cmath>
#include <limits>

#include "board/tracking.hpp"
#include "board/views.hpp"
#include "lens/reference_models.hpp"
#include "select/engine.hpp"
#include "session/session.hpp"
#include "sim/sim_camera.hpp"
#include "sim/synthetic.hpp"

using namespace posecal;

namespace {

struct Rig {
  CameraModel cam = c525_reference_model();
  Board board;
  SyntheticCamera sc;
  Rig() : sc(cam, board, render_options()) {}
  static RenderOptions render_options() {
    RenderOptions ro;
    ro.noise_sigma = 2;
    ro.blur_sigma_px = 0.8;
    ro.seed = 7;
    return ro;
  }
  // The board at `centre` (camera frame, metres) tilted by `tilt_deg` about an in-plane axis.
  cv::Mat frame(const Eigen::Vector3d& centre, double tilt_deg, double axis_rad = 0.3) {
    return sc.render(board_pose_at(board, centre, axis_rad, tilt_deg * M_PI / 180, 0.05));
  }
};

double worst_difference(const Detection& a, const Detection& b) {
  double worst = 0;
  for (size_t i = 0; i < a.size(); ++i)
    worst = std::max(worst, cv::norm(a.image_points[i] - b.image_points[i]));
  return worst;
}

}  // namespace

// Near and far, flat and tilted: the tracked search (region, shrunk copy, markers of the known
// size at one threshold window) finds every corner of the whole-frame search, refined to the
// same saddle; a near board is searched on a shrunk copy.
TEST(Tracking, TrackedSearchFindsTheWholeFrameCorners) {
  Rig rig;
  int shrunk = 0;
  for (const double z : {0.3, 0.45, 0.7}) {
    for (const double tilt : {0.0, 30.0, 50.0}) {
      const cv::Mat img = rig.frame(Eigen::Vector3d(0.02, -0.01, z), tilt);
      const Detection whole = rig.board.detect(img);
      ASSERT_GE(whole.size(), 20u) << z << " " << tilt;
      const TrackingPlan plan = plan_tracking(rig.board, whole, img.size());
      ASSERT_FALSE(plan.region.empty());
      EXPECT_LT(plan.region.area(), static_cast<int>(img.total()) + 1);
      if (plan.shrink > 1) ++shrunk;
      const Detection tracked = rig.board.detect_in(img, plan.region, plan.shrink,
                                                    plan.min_perimeter_px, plan.max_perimeter_px);
      ASSERT_EQ(tracked.ids, whole.ids)
          << "z " << z << " tilt " << tilt << " shrink " << plan.shrink;
      EXPECT_LT(worst_difference(tracked, whole), 0.02) << "z " << z << " tilt " << tilt;
    }
  }
  EXPECT_GE(shrunk, 3);  // the near boards
}

// The board jumps by a third of the image between two frames: the tracked search around its old
// place finds fewer corners, so the whole frame is searched and its result returned; the next
// frame is tracked again from there.
TEST(Tracking, FallsBackToTheWholeFrameWhenTheBoardLeftTheRegion) {
  Rig rig;
  BoardTracker tracker;
  const cv::Mat here = rig.frame(Eigen::Vector3d(-0.12, 0, 0.7), 10);
  const cv::Mat there = rig.frame(Eigen::Vector3d(0.12, 0, 0.7), 10);
  const Detection first = tracker.detect(rig.board, here, {});
  ASSERT_GE(first.size(), 30u);
  EXPECT_EQ(tracker.counts().whole, 1u);
  const Detection jumped = tracker.detect(rig.board, there, {});
  EXPECT_EQ(tracker.counts().fallback, 1u);
  EXPECT_FALSE(tracker.last_was_tracked());
  const Detection whole = rig.board.detect(there);
  EXPECT_EQ(jumped.ids, whole.ids);
  EXPECT_EQ(worst_difference(jumped, whole), 0.0);
  tracker.detect(rig.board, there, {});
  EXPECT_EQ(tracker.counts().tracked, 1u);
  EXPECT_TRUE(tracker.last_was_tracked());
  // No board: the whole frame is searched every time, and reset() forgets the board.
  tracker.reset();
  tracker.detect(rig.board, there, {});
  EXPECT_EQ(tracker.counts().whole, 2u);
}

// A board searched every 15 tracked frames in the whole frame all the same.
TEST(Tracking, SearchesTheWholeFrameEveryFifteenFrames) {
  Rig rig;
  BoardTracker tracker;
  const cv::Mat img = rig.frame(Eigen::Vector3d(0, 0, 0.5), 20);
  for (int i = 0; i < 32; ++i) tracker.detect(rig.board, img, {});
  EXPECT_EQ(tracker.counts().fallback, 0u);
  EXPECT_EQ(tracker.counts().whole, 2u);  // frames 1 and 17; 2-16 and 18-32 tracked
  EXPECT_EQ(tracker.counts().tracked, 30u);
}

// Regions and bounds that make no sense find nothing or are ignored, never crash.
TEST(Tracking, BadRegionsAndBoundsAreHarmless) {
  Rig rig;
  const cv::Mat img = rig.frame(Eigen::Vector3d(0, 0, 0.5), 20);
  const double nan = std::numeric_limits<double>::quiet_NaN();
  EXPECT_TRUE(rig.board.detect_in(img, cv::Rect(5000, 5000, 10, 10), 2).empty());
  EXPECT_TRUE(rig.board.detect_in(img, cv::Rect(0, 0, 0, 0), 1).empty());
  EXPECT_TRUE(rig.board.detect_in(img, cv::Rect(0, 0, 3, 3), 1).empty());
  const Detection whole = rig.board.detect(img);
  EXPECT_EQ(rig.board.detect_in(img, cv::Rect(-100, -100, 5000, 5000), 0, nan, nan).ids, whole.ids);
  EXPECT_EQ(rig.board.detect_in(img, cv::Rect(0, 0, img.cols, img.rows), 1, 50, 10).ids, whole.ids);
  EXPECT_TRUE(plan_tracking(rig.board, Detection{}, img.size()).region.empty());
  EXPECT_THROW(rig.board.detect_in(cv::Mat(), cv::Rect(0, 0, 10, 10), 1), Error);
  // A plan for a motion of NaN or of a huge number of pixels stays inside the frame.
  const TrackingPlan plan = plan_tracking(rig.board, whole, img.size(), {}, {nan, 1e300});
  EXPECT_EQ(plan.region & cv::Rect(0, 0, img.cols, img.rows), plan.region);
}

// A simulated person's session with tracking (the default): most frames are tracked, and every
// keyframe is exactly the whole-frame search of the frame it was captured in.
TEST(Tracking, EngineKeyframesAreWholeFrameSearches) {
  const Uri uri = Uri::parse("sim://?seed=11");
  SimCameraOptions so = sim_options_from_uri(uri, BoardSpec{});
  EngineOptions eo;
  eo.target_timeout_frames = 36;
  ASSERT_TRUE(eo.track_board);
  CalibrationSession s(make_sim_camera(so), eo);
  int checked = 0;
  for (int f = 0; f < 1500 && !s.finished(); ++f) {
    const int before = s.engine_ptr() ? s.engine().keyframes() : 0;
    s.step(1000);
    if (s.engine_ptr() && s.engine().keyframes() > before) {
      const Detection whole = s.engine().board().detect(s.last_frame());
      const Observation& kf = s.engine().keyframe_observations().back();
      ASSERT_EQ(kf.ids, whole.ids);
      for (size_t i = 0; i < whole.size(); ++i)
        ASSERT_EQ(kf.image_points[i], whole.image_points[i]);
      ++checked;
    }
  }
  EXPECT_TRUE(s.engine().converged()) << s.engine().failure_reason();
  EXPECT_EQ(checked, s.engine().keyframes());
  const BoardTracker::Counts& c = s.engine().board_search_counts();
  std::printf("board searches: %llu tracked, %llu fallback, %llu whole\n",
              static_cast<unsigned long long>(c.tracked),
              static_cast<unsigned long long>(c.fallback),
              static_cast<unsigned long long>(c.whole));
  EXPECT_GT(c.tracked, 2 * (c.fallback + c.whole));
  EXPECT_LT(c.fallback, c.tracked / 10 + 1);
}
