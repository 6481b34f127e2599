#include "evaluation.hpp"

#include "abi_common.hpp"
#include "calib/metrics.hpp"
#include "sim/synthetic.hpp"

namespace posecal::abi {

std::vector<Observation> sim_test_set(const SimCameraOptions& options) {
  SyntheticCamera camera(options.truth, Board(options.board), options.render);
  return render_test_set(camera, 50);
}

nlohmann::json evaluation_json(const CameraModel& estimate,
                               const std::vector<Observation>& test_set, const CameraModel* truth) {
  nlohmann::json j;
  const TestError te = test_error(estimate, test_set);
  j["eps_test"] = te.frames_used > 0 ? number(te.rms_px) : nlohmann::json(nullptr);
  j["test_frames"] = te.frames_used;
  j["test_frames_failed"] = te.frames_failed;
  j["test_points"] = te.points;
  j["eps_gt"] = truth ? number(ground_truth_error(*truth, estimate)) : nlohmann::json(nullptr);
  // The same with the camera frame's rotation, which the images cannot determine, taken out.
  j["eps_gt_aligned"] =
      truth ? number(ground_truth_error_aligned(*truth, estimate)) : nlohmann::json(nullptr);
  return j;
}

}  // namespace posecal::abi
