// JSON and file output of calibration results, shared by every ABI call that reports one.
#pragma once

#include <nlohmann/json.hpp>
#include <string>
#include <utility>
#include <vector>

#include "calib/calibration.hpp"
#include "device/camera.hpp"

namespace posecal::abi {

nlohmann::json device_json(const DeviceInfo& d);
// Values, "std" (scaled by the residual variance: the honest sigma), "std_unit" (Sigma_p = I,
// paper eq. 5), index of dispersion, "rms", per-frame RMS, intrinsics covariance (scaled).
nlohmann::json calibration_json(const CalibrationResult& r);
// OpenCV YAML (.yml/.yaml) or JSON (.json) with nr_of_frames, avg_reprojection_error and the
// per-parameter standard deviations.
void save_calibration(const std::string& path, const CalibrationResult& r,
                      const std::vector<std::pair<std::string, std::string>>& extra_strings);

}  // namespace posecal::abi
