// sim://: a camera whose frames the synthetic renderer draws of the board where the simulated
// operator holds it, guided by the engine; and the evaluation of a synthetic calibration.
#pragma once

#include <cstdint>
#include <memory>

#include "calib/calibration.hpp"
#include "device/camera.hpp"
#include "device/sources.hpp"
#include "sim/operator.hpp"
#include "sim/synthetic.hpp"

namespace posecal {

struct SimCameraOptions {
  CameraModel truth;          // ground truth camera
  BoardSpec board;
  RenderOptions render;       // noise, blur, seed...
  OperatorOptions op;
  uint64_t seed = 1;
};

// Parses sim://?model=FILE&seed=N&operator=NAME&noise=G&blur=PX&renderer=raycast|warp into
// options (every parameter optional; default camera sampled around the C525 with 10% std;
// operator: person (= approach) or an operator_preset name).
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
