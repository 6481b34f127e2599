// The paper's compactness test (calib/compactness.hpp).
#include <gtest/gtest.h>

#include <algorithm>
#include <set>

#include "board/views.hpp"
#include "calib/compactness.hpp"
#include "calib/metrics.hpp"
#include "common/error.hpp"
#include "lens/reference_models.hpp"
#include "sim/sim_camera.hpp"

using namespace posecal;

TEST(Compactness, GreedySubsetStopsWhereNoKeyframeHelps) {
  const CameraModel truth = sample_camera(c525_reference_model(), 0.1, 4);
  const Board board;
  RenderOptions ro;
  ro.noise_sigma = 2;
  ro.blur_sigma_px = 0.8;
  SyntheticCamera cam(truth, board, ro);
  ViewSampling vs;
  vs.max_tilt_deg = 45;
  std::vector<Observation> keyframes;
  for (const Pose& p : random_board_views(21, 9, truth, board, vs)) {
    const Detection d = board.detect(cam.render(p));
    if (d.size() >= 20) keyframes.push_back(Observation::from(d));
  }
  // A repeated view adds (almost) nothing.
  keyframes.push_back(keyframes[2]);
  ASSERT_GE(keyframes.size(), 8u);
  SyntheticCamera test_cam(truth, board, ro);
  const std::vector<Observation> test = render_test_set(test_cam, 20);
  const CompactSubset c = greedy_compact_subset(keyframes, test, truth.size());
  ASSERT_GE(c.keyframes.size(), 2u);
  EXPECT_EQ(c.keyframes[0], 0);
  EXPECT_EQ(c.keyframes[1], 1);
  EXPECT_EQ(std::set<int>(c.keyframes.begin(), c.keyframes.end()).size(), c.keyframes.size());
  // eps_test is the subset's own, and no remaining keyframe lowers it.
  std::vector<Observation> subset;
  for (int i : c.keyframes) subset.push_back(keyframes[i]);
  EXPECT_NEAR(test_error(calibrate(subset, truth.size()).model, test).rms_px, c.eps_test, 1e-9);
  for (int i = 0; i < static_cast<int>(keyframes.size()); ++i) {
    if (std::count(c.keyframes.begin(), c.keyframes.end(), i)) continue;
    subset.push_back(keyframes[i]);
    EXPECT_GE(test_error(calibrate(subset, truth.size()).model, test).rms_px, c.eps_test - 1e-9) << i;
    subset.pop_back();
  }
  EXPECT_NEAR(test_error(calibrate(keyframes, truth.size()).model, test).rms_px, c.eps_test_all, 1e-9);
  std::printf("kept %zu of %zu keyframes: eps_test %.4f (all: %.4f)\n", c.keyframes.size(), keyframes.size(),
              c.eps_test, c.eps_test_all);
  // Bad input.
  EXPECT_THROW(greedy_compact_subset({keyframes[0]}, test, truth.size()), Error);
  EXPECT_THROW(greedy_compact_subset(keyframes, {}, truth.size()), Error);
  EXPECT_THROW(greedy_compact_subset(keyframes, test, truth.size(), {}, 1), Error);
}
