// What the engine wants next, in terms a camera that acts on it understands: guided cameras (the
// simulated operator of sim://, a robot cell's driver) move the board to the target; real cameras
// ignore it (Camera::guide).
#pragma once

#include <cstdint>

#include "lens/camera_model.hpp"
#include "lens/geometry.hpp"

namespace posecal {

// Which rule made a target pose (paper §3.3, §3.4; kView: EngineOptions::view_candidates).
enum class TargetKind {
  kInitTilted,          // first initial pose, tilted about x
  kInitFrontoParallel,  // second initial pose, parallel to the image plane covering the view
  kPinhole,             // C_K pose for fx fy cx cy
  kDistortion,          // C_Delta pose for the distortion coefficients
  kView,                // a generic whole-board view
};
// "init-tilted", "init-fronto-parallel", "pinhole", "distortion", "view" (events, JSON, statistics).
const char* target_kind_name(TargetKind kind);

struct GuidanceInfo {
  bool has_target = false;     // false while waiting for the board / after convergence
  bool bootstrapping = false;  // no calibration yet: show the board roughly fronto-parallel
  bool robot = false;          // target is to be reached literally (6-DoF), not by overlay
  Pose T_cam_board_target;     // target board pose in the camera frame
  CameraModel estimate;        // current intrinsics, used to draw the overlay
  uint64_t target_serial = 0;  // increments with every new target
  TargetKind target_kind = TargetKind::kInitTilted;  // meaningful with has_target
  int keyframes = 0;           // keyframes captured so far
  bool finished = false;       // converged or failed: nothing more to show
};

}  // namespace posecal
