// JSON and file output of calibration results, shared by every ABI call that reports one.
#pragma once

#include <nlohmann/json.hpp>
#include <string>
#include <utility>
#include <vector>

#include "calib/calibration.hpp"
#include "device/camera.hpp"
#include "io/model_file.hpp"
#include "select/engine.hpp"

namespace posecal::abi {

nlohmann::json device_json(const DeviceInfo& d);
// Values, "std" (scaled by the residual variance: the honest sigma), "std_unit" (Sigma_p = I,
// paper eq. 5), index of dispersion, "rms", per-frame RMS, intrinsics covariance (scaled).
nlohmann::json calibration_json(const CalibrationResult& r);
// The automatic lens model's evidence (CalibrationEngine::lens_candidates): the model chosen,
// the criterion and every candidate's figures.
nlohmann::json lens_choice_json(const CalibrationEngine& engine);
// Writes the result as a camera-model file (io/model_file.hpp) in `format` (a format name; NULL
// or "": by the extension), with the figures of the result: nr_of_frames,
// avg_reprojection_error, the per-parameter standard deviations, the intrinsics covariance and
// the expected error (where the format holds them), and the caller's strings and flags in
// `extras`. Error(kInvalidArgument) for an unknown format or a model the format cannot hold;
// nothing is written then.
void save_calibration(const std::string& path, const CalibrationResult& r, const char* format,
                      CalibrationFileExtras extras);

}  // namespace posecal::abi
