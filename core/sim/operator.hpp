// The simulated operator of the closed loop: a person who aligns the board with the overlay (drawn
// with the engine's current, imperfect intrinsics) or a robot that goes to the 6-DoF target, each
// with realistic error; and cameras sampled around a reference (paper §5.1).
#pragma once

#include <cstdint>
#include <map>
#include <random>
#include <string>

#include "board/board.hpp"
#include "device/guidance.hpp"
#include "lens/camera_model.hpp"

namespace posecal {

enum class OperatorKind { kPerson, kRobot };

// What a person shows before the engine has a target (the bootstrap).
enum class BootstrapBoards {
  // Roughly fronto-parallel near the centre, then follows the guidance "tilt the board": each
  // further attempt about 10 degrees more (paper §3.4).
  kFollowsGuidance,
  // Does not read the guidance: centred (within 10% of the view), 55% of the image width,
  // tilted 10-25 degrees about a random axis, every attempt.
  kFixedTilt,
  // Does not read the guidance either: any board that shows all its corners, 30-90% of the
  // width, tilted 0-60 degrees about a random axis, anywhere in the view.
  kAnyBoard,
};

struct OperatorOptions {
  OperatorKind kind = OperatorKind::kPerson;
  BootstrapBoards bootstrap = BootstrapBoards::kFollowsGuidance;
  double rotation_error_deg = 2.0;          // N(0, 2 deg) per axis
  double translation_error_fraction = 0.02; // N(0, 2% of the distance) per axis
  int move_frames = 3;                      // frames spent moving to a new attempt (0: appears there)
  int hold_frames = 4;                      // frames held still per attempt
  double jitter_px = 0.2;                   // sub-pixel hand tremor while holding
  int max_tries = 5;                        // attempts per target before giving up
  bool is_valid(std::string* error) const;
};

// The operators of the benchmark's worlds (docs/benchmarks.md), by name:
//   "approach"  a person who approaches each target over 3 frames and holds it 4 (the default),
//   "hold-only" one who is simply there and holds exactly 3 frames per try, and bootstraps with
//               a centred board tilted 10-25 degrees whatever the guidance says (kFixedTilt),
//   "sloppy"    "approach" with twice the alignment error (4 degrees, 4% of the distance),
//   "careless"  "hold-only" who shows any board while bootstrapping (kAnyBoard),
//   "robot"     a robot at the 6-DoF target (2 degrees, 2%).
// Throws Error(kInvalidArgument) naming the choices for an unknown name.
OperatorOptions operator_preset(const std::string& name);
extern const char* const kOperatorPresetNames;  // "approach, hold-only, sloppy, careless, robot"


// Per target kind: how often an attempt ended in a capture.
struct AttemptStats {
  int attempts = 0;
  int reached = 0;
};

class SimulatedOperator {
 public:
  SimulatedOperator(const CameraModel& truth, const Board& board, const OperatorOptions& options,
                    uint64_t seed);
  // The board pose for the next frame, given the engine's current guidance.
  Pose next_pose(const GuidanceInfo& guidance);
  // Robots: true once per attempt when the board has arrived and is held.
  bool take_pose_reached();
  const std::map<std::string, AttemptStats>& attempts() const { return stats_; }
  bool gave_up() const { return gave_up_; }

 private:
  Pose attempt_goal(const GuidanceInfo& g);
  Pose bootstrap_goal();
  Pose board_at(double width_fraction, const Eigen::Vector2d& centre_px, const Eigen::Matrix3d& R) const;
  Pose perturb(const Pose& p);

  CameraModel truth_;
  Board board_;
  OperatorOptions opt_;
  std::mt19937_64 rng_;
  Pose current_, from_, goal_;
  bool have_current_ = false;
  uint64_t serial_ = ~0ull;
  int keyframes_seen_ = 0;
  std::string kind_;
  int phase_frame_ = 0;
  int tries_ = 0;
  bool in_attempt_ = false;
  bool gave_up_ = false;
  bool reached_signal_ = false;
  std::map<std::string, AttemptStats> stats_;
};

// A camera sampled around a reference: every parameter ~ N(C, (rel_std * C)^2) (paper §5.1,
// eq. 9). Resampled until the model is valid and has no fold-over inside the image.
CameraModel sample_camera(const CameraModel& reference, double rel_std, uint64_t seed);

}  // namespace posecal
