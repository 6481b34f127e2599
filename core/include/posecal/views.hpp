// Board views for synthetic experiments: random well-spread poses (the OpenCV baselines of the
// benchmarks), the fixed test set for eps_test, and visibility checks.
#pragma once

#include <cstdint>
#include <optional>
#include <random>
#include <vector>

#include "posecal/camera_model.hpp"
#include "posecal/geometry.hpp"
#include "posecal/target.hpp"

namespace posecal {

// Board pose with the board's centre at `centre_cam` (camera frame), rotated from fronto-parallel
// (R = I: board x to the image's right, y down) by `tilt_rad` about the in-plane axis at angle
// `tilt_axis_rad` from the image x axis, then rolled by `roll_rad` about the optical axis.
Pose board_pose_at(const Target& target, const Eigen::Vector3d& centre_cam, double tilt_axis_rad,
                   double tilt_rad, double roll_rad);

// True if the whole board (its outline, sampled densely, and every corner) projects inside the
// image with `margin_px` to spare, in front of the camera.
bool board_fully_visible(const CameraModel& model, const Target& target, const Pose& T_cam_board,
                         double margin_px = 2.0);

struct ViewSampling {
  double max_tilt_deg = 45.0;
  double min_width_fraction = 0.3;  // board width in the image, as a fraction of image width
  double max_width_fraction = 0.7;
  double margin_px = 4.0;
  int max_tries = 2000;
};

// A random view with the board fully visible, or nullopt if none was found in max_tries.
// `draws` (optional) receives the number of draws it took.
std::optional<Pose> random_board_view(std::mt19937_64& rng, const CameraModel& model,
                                      const Target& target, const ViewSampling& sampling = {},
                                      int* draws = nullptr);

// `count` random views (throws Error(kInternal) if the camera cannot see the board at all).
std::vector<Pose> random_board_views(uint64_t seed, int count, const CameraModel& model,
                                     const Target& target, const ViewSampling& sampling = {});

// The fixed synthetic test set for eps_test: 50 views at various distances (board 20-80% of the
// image width) and angles (tilt up to 50 deg) covering the whole view. Deterministic.
std::vector<Pose> test_set_views(const CameraModel& model, const Target& target, int count = 50);

}  // namespace posecal
