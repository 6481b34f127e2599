// Test-set evaluation shared by posecal_session_result (sim:// sessions) and posecal_evaluate.
#pragma once

#include <nlohmann/json.hpp>
#include <vector>

#include "calib/calibration.hpp"
#include "sim/sim_camera.hpp"

namespace posecal::abi {

// The fixed 50-frame test set of a simulated camera, rendered by a fresh synthetic camera with
// the same truth, board and render options (seed): the same frames for a live session and for a
// later posecal_evaluate of its saved result, and rendering it never changes the noise of the
// session's own frames.
std::vector<Observation> sim_test_set(const SimCameraOptions& options);

// "eps_test", "test_frames", "test_frames_failed", "test_points" and, with a truth,
// "eps_gt" of `estimate` on `test_set`.
nlohmann::json evaluation_json(const CameraModel& estimate,
                               const std::vector<Observation>& test_set, const CameraModel* truth);

}  // namespace posecal::abi
