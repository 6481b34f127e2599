// Closed-loop simulation: a simulated operator (person or robot) moves the synthetic board to
// the engine's targets with realistic error; the sim:// camera renders what the camera sees.
#pragma once

#include <cstdint>
#include <map>
#include <memory>
#include <random>
#include <string>

#include "device/camera.hpp"
#include "device/sources.hpp"
#include "select/engine.hpp"
#include "sim/synthetic.hpp"

namespace posecal {

enum class OperatorKind { kPerson, kRobot };

struct OperatorOptions {
  OperatorKind kind = OperatorKind::kPerson;
  double rotation_error_deg = 2.0;          // N(0, 2 deg) per axis
  double translation_error_fraction = 0.02; // N(0, 2% of the distance) per axis
  int move_frames = 3;                      // frames spent moving to a new attempt
  int hold_frames = 4;                      // frames held still per attempt
  double jitter_px = 0.2;                   // sub-pixel hand tremor while holding
  int max_tries = 5;                        // attempts per target before giving up
  bool is_valid(std::string* error) const;
};

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

struct SimCameraOptions {
  CameraModel truth;          // ground truth camera
  BoardSpec board;
  RenderOptions render;       // noise, blur, seed...
  OperatorOptions op;
  uint64_t seed = 1;
};

// Parses sim://?model=FILE&seed=N&operator=person|robot&noise=G&blur=PX into options (every
// parameter optional; default camera sampled around the C525 with 10% std).
SimCameraOptions sim_options_from_uri(const Uri& uri, const BoardSpec& board);

class SimCamera;
std::shared_ptr<CameraBackend> make_sim_backend(const BoardSpec& board = {});
std::unique_ptr<Camera> make_sim_camera(const SimCameraOptions& options);
// The simulated camera behind a Camera (nullptr if it is not one).
SimCamera* as_sim_camera(Camera* camera);

class SimCamera : public SimpleCamera {
 public:
  virtual const CameraModel& truth() const = 0;
  virtual SyntheticCamera& synthetic() = 0;
  virtual const SimulatedOperator& op() const = 0;
  virtual const SimCameraOptions& sim_options() const = 0;

 protected:
  using SimpleCamera::SimpleCamera;
};

// Evaluation of a synthetic calibration: eps_test on the fixed 50-frame test set rendered by
// the same synthetic camera (same noise), eps_gt against the ground truth.
struct SimEvaluation {
  double eps_test = -1;
  int test_frames = 0;
  double eps_gt = -1;
};
// Renders the fixed test set (test_set_views) with `camera` and detects it; frames where less
// than half the board is detected are left out.
std::vector<Observation> render_test_set(SyntheticCamera& camera, int count = 50);
SimEvaluation evaluate_synthetic(const CameraModel& estimate, const CameraModel& truth,
                                 const std::vector<Observation>& test_set);

}  // namespace posecal
